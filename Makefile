# Every target builds .venv from requirements.txt first when it is missing or stale.
PY := .venv/bin/python
VENV_STAMP := .venv/.requirements-installed

.PHONY: demo test lint bench extension test-blender clean-venv

$(VENV_STAMP): requirements.txt
	test -x $(PY) || python3.11 -m venv .venv || python3 -m venv .venv
	$(PY) -m pip install --upgrade pip
	$(PY) -m pip install -r requirements.txt
	touch $(VENV_STAMP)

demo: $(VENV_STAMP)
	$(PY) standalone/run.py demo --out-dir out/demo

test: $(VENV_STAMP)
	$(PY) -m pytest -q tests

lint: $(VENV_STAMP)
	$(PY) -m ruff check .

bench: $(VENV_STAMP)
	$(PY) standalone/run.py bench

# The Blender extension: one zip per platform (linux-x64, windows-x64, macos-arm64, macos-x64)
# with scipy, safetensors, laspy and lazrs bundled as wheels for Python 3.11 and 3.13
# (tools/build_extension.py: pip download, cached in .cache/wheels; validated and built with
# Blender's own blender_ext.py). `make extension DIST=dir PLATFORMS="linux-x64"` for fewer.
extension: $(VENV_STAMP)
	$(PY) tools/build_extension.py --dist "$(or $(DIST),dist)" $(if $(PLATFORMS),--platforms $(PLATFORMS))

# The extension tests against the bpy wheel of another Blender (4.2 LTS, 4.5 LTS): a venv in
# .cache/venv-bpy-<version> with that bpy, numpy<2 (what Blender ships) and the rest of
# requirements.txt (the command line the tests compare with needs it); the installed extension
# gets its packages from its bundled wheels, and tests/test_extension_bare.py checks that with
# bpy alone. `make test-blender BPY=4.2.23`.
BPY ?= 4.2.23
BPY_VENV := .cache/venv-bpy-$(BPY)
test-blender: $(VENV_STAMP)
	test -x $(BPY_VENV)/bin/python || python3.11 -m venv $(BPY_VENV)
	grep -v -E '^(bpy|cgal|ruff)==' requirements.txt > $(BPY_VENV)/requirements-matrix.txt
	$(BPY_VENV)/bin/python -m pip install --quiet "bpy==$(BPY)" "numpy<2" -r $(BPY_VENV)/requirements-matrix.txt
	$(BPY_VENV)/bin/python -m pytest -q tests/test_extension.py tests/test_extension_ops.py \
		tests/test_extension_las.py tests/test_extension_bare.py

clean-venv:
	rm -rf .venv
