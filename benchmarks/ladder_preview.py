"""A preview of the learner's ladder (issue #61) on an accelerator: every synthetic rung and seed side by side, each
process training on the device and measuring on CPU copies of its actor (rlsac.experiments.ladder, device="cuda"). Not
the record: the committed runs are CPU-made (`rlsac scale --stage ladder`); this confirms them, never replaces them.

    python benchmarks/ladder_preview.py OUT_DIR [--device cuda] [--steps N] [--rungs a,b] [--seeds 0,1,2]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import yaml

ONE = ("import json, sys, yaml; from rlsac.experiments.ladder import run; p = yaml.safe_load(open('params.yaml')); "
       "p['ladder'].update(json.loads(sys.argv[1])); print(run(p, sys.argv[2], int(sys.argv[3]), 1, sys.argv[4]))")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--steps", type=int, default=0, help="0: params.yaml ladder.steps")
    ap.add_argument("--rungs", default="control-0.3,control-0.45,control-0.6,rung0,rung1,rung2")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--override", default="{}", help="JSON merged into params ladder (e.g. sizes for a dry run)")
    a = ap.parse_args()
    over = json.loads(a.override) | ({"steps": a.steps} if a.steps else {})
    procs, t0 = [], time.time()
    for rung in a.rungs.split(","):
        for seed in a.seeds.split(","):
            log = open(Path(a.out) / f"{rung}-s{seed}.log", "w")
            procs.append((rung, seed, subprocess.Popen([sys.executable, "-c", ONE, json.dumps(over), rung, seed,
                                                        a.device], stdout=log, stderr=subprocess.STDOUT)))
    for rung, seed, p in procs:
        print(rung, seed, "rc", p.wait(), f"{time.time() - t0:.0f} s", flush=True)
    print(yaml.safe_dump({"seconds": round(time.time() - t0)}))


if __name__ == "__main__":
    main()
