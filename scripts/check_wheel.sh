#!/usr/bin/env bash
# The wheel works outside the checkout: build it, install it into a fresh virtual environment
# (dependencies from the package index; pip's cache makes repeat runs fast) and, from an empty
# temporary folder, run `ppr --version`, `ppr brdf`, `ppr simulate` on the shipped default
# configs (with a few --set / flags keeping them small) and the README's Python example
# (taken from README.md between its check_wheel markers, so the two cannot drift).
# CPU only; needs python3 >= 3.11 and the package index. Called by .ci/run after `make test`.
#
#   scripts/check_wheel.sh            # PYTHON=python3.12 scripts/check_wheel.sh to pick one
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
PYTHON="${PYTHON:-python3}"
tmp="$(mktemp -d "${TMPDIR:-/tmp}/ppr-check-wheel.XXXXXX")"
trap 'rm -rf "$tmp"' EXIT
start=$SECONDS
step() { printf 'check_wheel [%3d s] %s\n' "$((SECONDS - start))" "$*"; }

step "building the wheel"
"$PYTHON" -m pip wheel --quiet --no-deps --wheel-dir "$tmp/dist" "$repo"
wheel=("$tmp"/dist/ppr-*.whl)

step "installing $(basename "${wheel[0]}") into a fresh virtual environment"
"$PYTHON" -m venv "$tmp/venv"
"$tmp/venv/bin/python" -m pip install --quiet --no-compile --disable-pip-version-check "${wheel[0]}"

mkdir "$tmp/empty"
cd "$tmp/empty"
unset PYTHONPATH
export JAX_PLATFORMS=cpu MPLBACKEND=Agg PPR_JAX_CACHE=0
ppr="$tmp/venv/bin/ppr"

step "ppr --version"
"$ppr" --version
# the package in use is the installed one, not a checkout
"$tmp/venv/bin/python" - "$tmp/venv" <<'PY'
import sys
import ppr
assert ppr.__file__.startswith(sys.argv[1]), ppr.__file__
assert str(ppr.shipped_configs_dir()).startswith(sys.argv[1]), ppr.shipped_configs_dir()
assert "jax" not in sys.modules  # ppr.shipped_configs_dir is served without the library
PY

step "ppr brdf (shipped configs/cli/brdf.toml, single + multiple terms)"
"$ppr" brdf -q --out brdf --set 'terms=["single","multiple"]'
test -s brdf/brdf.npz && test -s brdf/brdf.json && test -s brdf/brdf.png

step "ppr simulate (shipped configs/scenes/cubesat3u_panels.toml, H and V, single bounce)"
"$ppr" simulate -q --out sim --states H,V --terms single --multibounce off \
    --set visibility.samples_per_face=1
test -s sim/simulate.npz && test -s sim/simulate.nc && test -s sim/simulate.json && test -s sim/simulate.png

step "the README's Python example"
awk '/<!-- check_wheel:python:start -->/{on=1; next} /<!-- check_wheel:python:end -->/{on=0}
     on && !/^```/' "$repo/README.md" > readme_example.py
test -s readme_example.py || { echo "check_wheel: no example between the README's markers" >&2; exit 1; }
"$tmp/venv/bin/python" readme_example.py

step "passed"
