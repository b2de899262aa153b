# Set-up and everyday commands. Each target installs what it needs into .venv first,
# so `make run` and `make test` work on a fresh clone.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
DATA   ?= data

# A regular (non-editable) install, redone only when a source file changed: the tests
# exercise the package as users get it.
STAMP   := $(VENV)/.installed
SOURCES := pyproject.toml CMakeLists.txt README.md \
           $(shell find native vastray server client -type f -not -name '*.pyc' -not -path '*/__pycache__/*' 2>/dev/null)

# Debian packages: Chromium for the browser tests (Playwright drives it; no browser
# download), liblz4 and libdeflate for the native block codecs, QEMU's user-mode
# emulator to run the module on CPUs without AVX (tests/test_isa_emulated.py).
APT_PACKAGES := chromium nginx openssl liblz4-dev libdeflate-dev pkg-config qemu-user
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: run test test-fast install dev bench lint clean tsan system-deps

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

$(STAMP): $(BIN)/python $(SOURCES)
	$(BIN)/pip install -q '.[test]'
	@touch $@

install: system-deps $(STAMP)

system-deps:
	@missing=""; for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
		echo "installing Debian packages:$$missing"; \
		$(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq --no-install-recommends $$missing; \
	fi

# Editable install for working on the code (rerun after changing C++).
dev: system-deps $(BIN)/python
	$(BIN)/pip install -q scikit-build-core pybind11
	$(BIN)/pip install -q --no-build-isolation -e '.[test,bench]'
	@rm -f $(STAMP)

# The main job: the render server with the built-in demo model (built on first start
# into $(DATA)/), printing the URL to open.
run: install
	$(BIN)/vastray serve --data $(DATA)

lint: install
	$(BIN)/ruff check .

test: lint
	$(BIN)/pytest

# The daily loop: everything but the tests marked slow (CI runs them all).
test-fast: lint
	$(BIN)/pytest -m "not slow" -x

# The native cache stress test under ThreadSanitizer (also part of `make test`).
tsan: install
	$(BIN)/cmake -S . -B build/tsan -G Ninja -DCMAKE_MAKE_PROGRAM=$(abspath $(BIN)/ninja) \
		-DCMAKE_BUILD_TYPE=RelWithDebInfo -DVASTRAY_PYTHON=OFF -DVASTRAY_NATIVE_TESTS=ON -DVASTRAY_TSAN=ON
	$(BIN)/cmake --build build/tsan --target cache_stress
	@mkdir -p out
	$(BIN)/vastray build scene:plant:40000:2 -o out/tsan-plant.vast --force
	$(BIN)/vastray build scene:spheres:30000:3 -o out/tsan-spheres.vast --force
	TSAN_OPTIONS="halt_on_error=1 exitcode=66" build/tsan/native/cache_stress out/tsan-plant.vast out/tsan-spheres.vast 60

bench: $(BIN)/python
	$(BIN)/pip install -q '.[bench]'
	$(BIN)/python bench/rays.py
	$(BIN)/python bench/build.py
	$(BIN)/python bench/tradeoff.py

clean:
	rm -rf build out .pytest_cache .ruff_cache $(STAMP)
