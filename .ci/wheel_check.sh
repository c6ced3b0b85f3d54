#!/usr/bin/env bash
# The wheel as a user gets it: build, install into a fresh venv, run every analyze method
# from outside the source tree (the shipped checkpoints must come from the wheel).
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$PWD
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
python3 -m venv "$work/venv"
. "$work/venv/bin/activate"
pip install -q -c .ci/constraints.txt torch==2.13.0
pip wheel -q --no-deps -w "$work/dist" .
pip install -q -c .ci/constraints.txt "$work"/dist/lensdist_torch-*.whl
cd "$work"
python "$repo/.ci/make_pair.py" "$work"
lensdist --version
for method in selfcal regression eigenspace; do
  lensdist analyze a.png b.png --method "$method" --json > "out_$method.json"
  python -c "import json, sys; r = json.load(open('out_$method.json')); assert r['registration_ok'], r; print('wheel: analyze --method $method ->', r['class'], round(r['delta_avg'], 2))"
done
python -c "import lensdist_torch, sys; assert 'site-packages' in lensdist_torch.__file__, lensdist_torch.__file__; print('wheel: imported from', lensdist_torch.__file__)"
