# rsl — two commands do everything on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
RSL    := $(VENV)/bin/rsl
OUT    ?= out
export JAX_ENABLE_X64 := 1
DEB_PACKAGES := libusb-1.0-0 libsuitesparse-dev libopenblas0-serial

.PHONY: setup demo test test-slow bench clean browser

setup: $(VENV)/.installed browser

# Debian's Chromium, for the headless-browser test of `rsl report` (tests/test_report.py), installed when
# missing; when it cannot be installed the test says so and skips its browser checks.
browser:
	@command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1 || { \
	  echo "installing Debian package: chromium"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  { $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq chromium; } || \
	  echo "chromium could not be installed: tests/test_report.py will skip its browser checks"; }

$(VENV)/.installed: pyproject.toml
	@# Debian packages: libusb for open3d; SuiteSparse headers and a serial OpenBLAS for CHOLMOD
	@missing=$$(for p in $(DEB_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || echo $$p; done); \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages: $$missing"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq $$missing; \
	fi
	test -d $(VENV) || $(PYTHON) -m venv $(VENV)
	# the pinned CPU wheel first: a plain `torch` would pull a CUDA build of several GB
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[test,cholmod]'
	touch $@

demo: setup
	bash docs/demo.sh $(OUT)

test: setup
	$(PY) -m pytest -q -n 2 --dist loadfile --durations=15

test-slow: setup
	$(PY) -m pytest -q -m slow

bench: setup
	for b in bench/*.py; do $(PY) $$b || exit 1; done

clean:
	rm -rf $(OUT)
