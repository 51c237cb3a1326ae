# Quick start: `make demo` and `make test` on a fresh machine; both create or reuse .venv.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# A CPU build of torch; a bare `torch` would pull a multi-GB CUDA build.
TORCH ?= torch==2.13.0

.PHONY: venv demo test bench-render clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q "$(TORCH)"
	$(BIN)/python -m pip install -q -e ".[server,cluster,video,data,mesh,bench,train,test,oidn,notebook]"
	touch $(STAMP)

demo: venv
	$(BIN)/isosr demo --out demo_out
	$(BIN)/isosr render proc:cloud:1@96 --size 512x512 --orbit 30,20,1.5 --outputs mask,normal,depth,ao,color \
		--ao-samples 32 -o demo_out/cloud_render.png

test: venv
	$(BIN)/python -m pytest -q

clean:
	rm -rf $(VENV) demo_out .pytest_cache
