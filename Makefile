# rsl — two commands do everything on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
RSL    := $(VENV)/bin/rsl
OUT    ?= out
export JAX_ENABLE_X64 := 1

.PHONY: setup demo test test-slow bench clean

setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	@# Debian packages: libusb for open3d, SuiteSparse headers for CHOLMOD (scikit-sparse)
	@if ! ldconfig -p | grep -q libusb-1.0 || [ ! -f /usr/include/suitesparse/cholmod.h ]; then \
	  echo "installing Debian's libusb-1.0-0 and libsuitesparse-dev"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq libusb-1.0-0 libsuitesparse-dev; \
	fi
	test -d $(VENV) || $(PYTHON) -m venv $(VENV)
	# the pinned CPU wheel first: a plain `torch` would pull a CUDA build of several GB
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[test,cholmod]'
	touch $@

demo: setup
	bash docs/demo.sh $(OUT)

test: setup
	$(PY) -m pytest -q -n 2 --dist loadfile

test-slow: setup
	$(PY) -m pytest -q -m slow

bench: setup
	for b in bench/*.py; do $(PY) $$b || exit 1; done

clean:
	rm -rf $(OUT)
