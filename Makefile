# The README commands:  `make demo`  (a picture gallery in a few minutes),  `make test`
# and  `make bench`  (the full benchmark). Each builds the environment first
# (idempotent), so a fresh clone needs nothing else.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo hero test test-all test-blender-versions bench addon official clean

$(STAMP): pyproject.toml constraints.txt scripts/setup.sh
	bash scripts/setup.sh $(PY) $(VENV)
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/mpib demo --out out/demo

# The README's picture (docs/images/hero.jpg and its figures, hero.json), from the demo.
hero: $(STAMP)
	$(BIN)/mpib demo --out out/demo --hero docs/images/hero.jpg

test: $(STAMP)
	$(BIN)/python -m pytest -m "not slow" -q

test-all: $(STAMP)
	$(BIN)/python -m pytest -q

# The Blender tests (marker `blender`) on bpy 4.2 LTS, 4.5 LTS and the newest 5.x, each
# in its own pinned virtualenv (.venv-bpy42, .venv-bpy45, .venv-bpy5x; Python 3.11, and
# 3.13 for 5.1+), built on first use: scripts/blender-versions.txt.
test-blender-versions:
	bash scripts/test_blender_versions.sh

# Every suite (quick mode; BENCH_FLAGS=--full for the full sample counts). The Cycles
# renders of the Blender suite take most of the first run and are cached after it.
BENCH_FLAGS ?=
bench: $(STAMP)
	$(BIN)/mpib bench --out out/bench $(BENCH_FLAGS)

# The optional extra for `mpib bench --suite official`: CPU torch 2.13.0 (about 200 MB).
# TORCH_INDEX is an extra index for the CPU build; empty (the default) uses pip's own
# indexes, which on the project's machines hold that CPU build. Elsewhere (PyPI's Linux
# torch is the CUDA one): make official TORCH_INDEX=https://download.pytorch.org/whl/cpu
TORCH_INDEX ?=
official: $(STAMP)
	$(BIN)/python -m pip install -q --disable-pip-version-check -c constraints.txt \
		$(if $(TORCH_INDEX),--extra-index-url $(TORCH_INDEX)) -e ".[official]"

# The Blender extension, one zip per platform: dist/mpib_refocus-<version>-<platform>.zip
# for windows_x64, macos_arm64, macos_x64 and linux_x64 (Blender's --split-platforms),
# each checked by scripts/check_addon.py as Blender would install it. The tests install
# and run the Linux zip; the Windows and macOS zips are built and checked, not run.
addon: $(STAMP)
	$(BIN)/python scripts/build_addon.py --out dist

clean:
	rm -rf $(VENV) .venv-bpy42 .venv-bpy45 .venv-bpy5x out dist blender_addon/wheels
