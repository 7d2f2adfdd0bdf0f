# Set-up is part of every target: uv is bootstrapped into .tools/ if it is not on PATH, then
# `uv sync --frozen` builds .venv from uv.lock (Python 3.11).
SHELL := /bin/bash
PYTHON ?= python3.11
UV := $(shell command -v uv 2>/dev/null || echo $(CURDIR)/.tools/bin/uv)
VENV_STAMP := .venv/.synced

.PHONY: demo test test-all lint setup clean

demo: $(VENV_STAMP)
	.venv/bin/lunarnav demo --out outputs/demo

test: $(VENV_STAMP)
	.venv/bin/python -m pytest

test-all: $(VENV_STAMP)
	.venv/bin/python -m pytest -m ""

lint: $(VENV_STAMP)
	.venv/bin/ruff check lunarnav_ml tests

setup: $(VENV_STAMP)

$(CURDIR)/.tools/bin/uv:
	$(PYTHON) -m venv .tools && .tools/bin/python -m pip install -q uv

$(VENV_STAMP): pyproject.toml uv.lock | $(UV)
	UV_PYTHON_DOWNLOADS=automatic $(UV) sync --frozen --extra dev --python $(PYTHON)
	touch $(VENV_STAMP)

clean:
	rm -rf .venv .tools outputs
