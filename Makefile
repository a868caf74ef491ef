# Every target builds .venv from requirements.txt first when it is missing or stale.
PY := .venv/bin/python
VENV_STAMP := .venv/.requirements-installed

.PHONY: demo test lint bench extension clean-venv

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

# The Blender extension zip (Edit > Preferences > Get Extensions > Install from Disk).
# Stages cljn_addon/ + blender_manifest.toml (no caches, no tests), validates and builds it with
# Blender's own blender_ext.py from the bpy wheel. `make extension DIST=dir` writes elsewhere.
extension: $(VENV_STAMP)
	@set -e; \
	dist="$(or $(DIST),dist)"; \
	ext="$$(ls .venv/lib/python3*/site-packages/bpy/*/scripts/addons_core/bl_pkg/cli/blender_ext.py | head -n 1)"; \
	test -n "$$ext" || { echo "blender_ext.py not found in the bpy wheel under .venv" >&2; exit 1; }; \
	tmp="$$(mktemp -d)"; trap 'rm -rf "$$tmp"' EXIT; \
	stage="$$tmp/cljn_denoise"; mkdir -p "$$stage" "$$dist"; \
	cp -R cljn_addon/. "$$stage/"; cp blender_manifest.toml "$$stage/"; \
	find "$$stage" -name __pycache__ -prune -exec rm -rf {} +; rm -rf "$$stage/tests"; \
	$(PY) "$$ext" validate "$$stage"; \
	$(PY) "$$ext" build --source-dir "$$stage" --output-dir "$$dist"

clean-venv:
	rm -rf .venv
