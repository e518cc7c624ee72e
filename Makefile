# The README's two commands: `make demo` and `make test`. Both set up .venv first.
PY ?= python3
VENV := .venv
VPY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: setup demo test bench clean

setup: $(STAMP)

# torch==2.13.0 first: a CPU build on this machine's disk; a bare torch requirement would pull a CUDA build.
$(STAMP): pyproject.toml
	test -x $(VPY) || $(PY) -m venv $(VENV)
	$(VPY) -m pip install --quiet --upgrade pip
	$(VPY) -m pip install --quiet torch==2.13.0
	$(VPY) -m pip install --quiet -e ".[all]"
	touch $(STAMP)

demo: setup
	$(VPY) -m experiments.demo

test: setup
	$(VPY) -m pytest -q

bench: setup
	$(VPY) -m experiments.benchmark_speed

# numba's cache (scr_env/jit.py): the per-user folder (python -m scr_env.jit prints it; ~/.cache/scr-dosing on
# Linux), $NUMBA_CACHE_DIR/scr-dosing if NUMBA_CACHE_DIR is set, and *.nbi/*.nbc files older versions left beside the
# sources
clean:
	-test -x $(VPY) && $(VPY) -m scr_env.jit --clear
	rm -rf "$${XDG_CACHE_HOME:-$$HOME/.cache}/scr-dosing"
	$(if $(NUMBA_CACHE_DIR),rm -rf "$(NUMBA_CACHE_DIR)/scr-dosing")
	rm -rf $(VENV) runs .pytest_cache .ruff_cache
	find scr_env ident control experiments tests -type f \( -name '*.nbi' -o -name '*.nbc' \) -delete
