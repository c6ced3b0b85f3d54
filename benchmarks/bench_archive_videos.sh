#!/usr/bin/env bash
# Issue 52's goal: 20 rendered videos (4 lenses, no lens among them, one unreadable, one of two frames)
# as one archive command, against 20 single runs; a rerun; a run killed mid-way and resumed.
# Usage: bash benchmarks/bench_archive_videos.sh [WORKDIR]   (needs the video extra: PyAV)
set -u
cd "${1:-/tmp/arch20}" && rm -rf vids A B single && mkdir -p vids single
PY=python; L=lensdist  # the installed library
$PY - <<'PY'
import av, numpy as np
from lensdist_torch.calibration import synthetic_sequence
lenses = [0.0, 1e-6, 4e-6, -2e-6]
for i in range(18):
    k2 = lenses[i % 4]
    fr, _ = synthetic_sequence(8, k2, 0.0, size=(240, 320), seed=i)
    with av.open(f"vids/v{i:02d}_k2_{k2:g}.mp4", "w") as c:
        s = c.add_stream("libx264", rate=10); s.width, s.height, s.pix_fmt, s.options = 320, 240, "yuv444p", {"crf": "0"}
        for f in fr:
            g = f[0].clamp(0, 1).mul(255).round().byte().numpy()
            c.mux(s.encode(av.VideoFrame.from_ndarray(np.repeat(g[..., None], 3, 2), format="rgb24")))
        c.mux(s.encode())
open("vids/v18_unreadable.mp4", "wb").write(b"not a video at all")
fr, _ = synthetic_sequence(2, 1e-6, 0.0, size=(240, 320))
with av.open("vids/v19_two_frames.mp4", "w") as c:
    s = c.add_stream("libx264", rate=10); s.width, s.height, s.pix_fmt, s.options = 320, 240, "yuv444p", {"crf": "0"}
    for f in fr:
        g = f[0].clamp(0, 1).mul(255).round().byte().numpy()
        c.mux(s.encode(av.VideoFrame.from_ndarray(np.repeat(g[..., None], 3, 2), format="rgb24")))
    c.mux(s.encode())
PY
ls vids | wc -l
t0=$(date +%s.%N); $L calibrate 'vids/*.mp4' --out A --method direct --quiet > A.txt 2>&1; echo "archive rc=$? $(echo "$(date +%s.%N) - $t0" | bc) s"
t0=$(date +%s.%N); for v in vids/*.mp4; do n=$(basename $v .mp4); $L calibrate $v --json --method direct --quiet > single/$n.json 2> single/$n.err; echo $? > single/$n.rc; done; echo "20 single runs $(echo "$(date +%s.%N) - $t0" | bc) s"
t0=$(date +%s.%N); $L calibrate 'vids/*.mp4' --out A --method direct --quiet > A2.txt 2>&1; echo "rerun rc=$? $(echo "$(date +%s.%N) - $t0" | bc) s"
# a killed run (SIGKILL: a background job ignores SIGINT) resumes to the same table
$L calibrate 'vids/*.mp4' --out B --method direct --quiet > B1.txt 2>&1 & pid=$!; sleep 15; kill -9 $pid; wait $pid; echo "killed rc=$?: $(ls B/answers 2>/dev/null | wc -l) answers"
$L calibrate 'vids/*.mp4' --out B --method direct --quiet > B2.txt 2>&1; echo "resumed rc=$?"
$PY - <<'PY'
import csv, json, glob, os
rows = list(csv.DictReader(open("A/answers.csv")))
print("rows", len(rows), "ok", sum(r["ok"] == "True" for r in rows))
same = 0; diff = []
for r in rows:
    n = os.path.basename(r["path"])[:-4]
    rc = open(f"single/{n}.rc").read().strip()
    ans = glob.glob(f"A/answers/{n}.mp4-*.json")
    if rc == "0" and ans:
        if open(ans[0]).read().strip() == open(f"single/{n}.json").read().strip(): same += 1
        else: diff.append(n)
    elif rc != "0":
        print("failed:", n, "| single:", open(f"single/{n}.err").read().strip()[:110], "| row:", (r["reason"] or "")[:110])
print("byte-identical answers:", same, "differ:", diff)
b = list(csv.DictReader(open("B/answers.csv")))
cols = [c for c in rows[0] if c not in ("seconds",)]
print("killed+resumed table equal (but seconds):", [{c: r[c] for c in cols} for r in rows] == [{c: r[c] for c in cols} for r in b])
for r in rows: print(os.path.basename(r["path"]), r["class"], r["delta_avg_user_px"][:6], r["reason"][:60])
PY
cat A2.txt | tail -3
