// Scratch arrays on the stack that cost nothing until used.
#pragma once

#include <new>

namespace vastray {

// Storage for N objects of type T that constructs none of them (placement new does, one
// by one, as they are needed): for per-call scratch arrays whose element types have
// default member initialisers, which a plain array would run for every element on every
// call (a tile's 256 pixels, a packet's 16 parted rays).
template <typename T, int N>
struct Uninitialised {
    alignas(T) unsigned char bytes[sizeof(T) * N];
    T* data() { return std::launder(reinterpret_cast<T*>(bytes)); }
};

}  // namespace vastray
