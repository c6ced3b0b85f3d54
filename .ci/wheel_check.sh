#!/usr/bin/env bash
# The wheel as a user gets it: build, install into a fresh venv, run every command of the README
# from outside the source tree (the shipped checkpoints must come from the wheel); generate
# / train / evaluate on 200 pairs rather than the full protocol, to keep CI short.
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$PWD
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
python3 -m venv "$work/venv"
. "$work/venv/bin/activate"
pip install -q -c .ci/constraints.txt torch==2.13.0
pip wheel -q --no-deps -w "$work/dist" .
whl=$(ls "$work"/dist/lensdist_torch-*.whl)
pip install -q -c .ci/constraints.txt "$whl[plots]"  # as the README: with the figures
cd "$work"
python "$repo/.ci/make_pair.py" "$work"
lensdist --version
for method in selfcal regression eigenspace; do
  lensdist analyze a.png b.png --method "$method" --json > "out_$method.json"
  python -c "import json, sys; r = json.load(open('out_$method.json')); assert r['registration_ok'], r; print('wheel: analyze --method $method ->', r['class'], r['estimated_delta_avg'] and round(r['estimated_delta_avg'], 2))"
done
lensdist analyze a.png b.png --save-map map.png | tee analyze.txt
test -s map.png && grep -q "Delta_avg" analyze.txt
lensdist demo --json --out demo > demo.json
python -c "import json; r = json.load(open('demo.json')); print('wheel: demo ->', sorted(r)[:4])"
lensdist calibrate frames/ --out calib/ --quiet
lensdist calibrate frames/ --json --quiet > calib.json
lensdist undistort frames/ --from calib/calibration.json --out corrected/ --quiet
python -c "import json, pathlib; r = json.load(open('calib.json')); n = len(list(pathlib.Path('corrected').glob('*.png'))); assert r['class'] == '4' and n == 10, (r, n); print('wheel: calibrate ->', r['class'], round(r['delta_avg_user_px'], 2), 'px; undistort ->', n, 'frames')"
lensdist generate --config "$repo/configs/paper.toml" --out data/paper --workers 2 --limit 200 --quiet
lensdist train --data data/paper --metric delta_avg --eigenvectors 10 --out checkpoints/mine.pt
lensdist evaluate --data data/paper --checkpoint checkpoints/mine.pt --out results/eval --quiet
lensdist reproduce --quick --out results/quick --quiet
test -s results/quick/reproduce.md && test -s results/eval/evaluate.json
python -c "import lensdist_torch, sys; assert 'site-packages' in lensdist_torch.__file__, lensdist_torch.__file__; print('wheel: imported from', lensdist_torch.__file__)"
