"""vastray: a render service for massive 3D models (out-of-core CPU ray tracing with LOD)."""

__version__ = "0.1.0"
