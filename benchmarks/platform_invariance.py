"""Which numeric settings change the record's bytes on this machine, what a portable pin costs, and whether the
pinned bytes stay put when MKL changes branch (the Intel/AMD difference of reports/platform.md).

    python benchmarks/platform_invariance.py [--mkl-intel-shim] [--workloads line_train,line_eval,...]

Each workload is a small `rlsac` command run in a fresh scratch folder (inputs linked from the repository; run it
from the repository root after `dvc repro lines_data import_scenes fold_data`), once per setting, in a child process
with the setting's environment (MKL, ATen, OpenBLAS, numpy and OpenCV read theirs at load time). It prints one row
per workload and setting: the md5 of the outputs (results only: timings and MLflow stay out), the wall seconds and
their ratio to the `default` row measured in the same run. Nothing is asserted: the times depend on the machine's
load, the hashes on its CPU.

Settings:
  default        the machine as it is
  mkl-intel      MKL on its Intel branch (--mkl-intel-shim: a preloaded library whose mkl_serv_intel_cpu_true
                 returns 1; built with gcc; only meaningful on a non-Intel CPU)
  aten-avx2      ATEN_CPU_CAPABILITY=avx2 (ATen's AVX2 kernels instead of AVX-512)
  openblas-skx   OPENBLAS_CORETYPE=SkylakeX (the kernels numpy's OpenBLAS picks on an Intel AVX-512 CPU)
  numpy-v3       NPY_DISABLE_CPU_FEATURES: numpy without its AVX-512 dispatch targets
  opencv-avx2    OPENCV_CPU_DISABLE: OpenCV without AVX-512
  onednn-avx2    ONEDNN_MAX_CPU_ISA=AVX2: oneDNN (torch's mkldnn ops) without AVX-512
  portable       RLSAC_NUMERICS=portable, all pins at once (rlsac.numerics.PINS): MKL_CBWR=COMPATIBLE, ATen AVX2,
                 oneDNN AVX2, OpenBLAS Haswell, numpy X86_V3, OpenCV AVX2
  portable+mkl-intel   the same with MKL on its Intel branch: equal hashes with `portable` mean the pins remove
                 MKL's vendor branch from the bytes
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rlsac import numerics

BIN = Path(sys.executable).parent
ROOT = Path.cwd()

# every variable a pin sets: none is inherited from the caller's environment, so each row sets only its own
PINNED = (*numerics.PINS, numerics.OPENCV_PIN[0], numerics.ENV)
NUMPY_AVX512 = numerics.PINS["NPY_DISABLE_CPU_FEATURES"]
OPENCV_AVX512 = numerics.OPENCV_PIN[1]
SETTINGS = {
    "default": {},
    "mkl-intel": {"@shim": "1"},
    "aten-avx2": {"ATEN_CPU_CAPABILITY": "avx2"},
    "openblas-skx": {"OPENBLAS_CORETYPE": "SkylakeX"},
    "numpy-v3": {"NPY_DISABLE_CPU_FEATURES": NUMPY_AVX512},
    "opencv-avx2": {"OPENCV_CPU_DISABLE": OPENCV_AVX512},
    "onednn-avx2": {"ONEDNN_MAX_CPU_ISA": "AVX2"},
    # the portable mode itself: rlsac sets its pins (rlsac.numerics.pins) when it is imported
    "portable": {"@mode": "portable"},
    "portable+mkl-intel": {"@mode": "portable", "@shim": "1"},
}
FOLD = "data/folds/hard/fountain"
# workload -> (inputs linked into the scratch folder, argv after `rlsac`, outputs hashed)
WORKLOADS = {
    "line_train": (["data/lines/train_o0.7.h5", "data/lines/val_o0.7.h5", "params.yaml"],
                   ["train", "--task", "line", "--data", "data/lines/train_o0.7.h5", "--val-data",
                    "data/lines/val_o0.7.h5", "--out", "out/l.pt", "--set", "sac.total_steps=200", "--set",
                    "sac.learning_starts=50", "--set", "val_every=100", "--set", "val_instances=100"], ["out"]),
    "line_eval": (["data/lines/test_o0.7.h5", "params.yaml"],
                  ["evaluate", "--task", "line", "--method", "ransac", "--data", "data/lines/test_o0.7.h5",
                   "--out-dir", "out"], ["out"]),
    "fold_data": (["data/raw/strecha", "params.yaml"],
                  ["folds", "--stage", "data", "--regime", "hard", "--fold", "fountain"], ["data/folds"]),
    "fold_train": ([f"{FOLD}/train.h5", f"{FOLD}/val.h5", "params.yaml"],
                   ["train", "--task", "fundamental", "--data", f"{FOLD}/train.h5", "--val-data", f"{FOLD}/val.h5",
                    "--out", "out/f.pt", "--set", "sac.total_steps=40", "--set", "sac.learning_starts=10", "--set",
                    "val_every=20", "--set", "val_instances=10"], ["out"]),
    "fold_eval_rlsac": ([f"{FOLD}/test.h5", "checkpoints/folds/hard/fountain/rlsac.pt", "params.yaml"],
                        ["evaluate", "--task", "fundamental", "--method", "rlsac", "--checkpoint",
                         "checkpoints/folds/hard/fountain/rlsac.pt", "--data", f"{FOLD}/test.h5", "--iterations",
                         "100", "--out-dir", "out"], ["out"]),
    "fold_eval_magsac": ([f"{FOLD}/test.h5", "params.yaml"],
                         ["evaluate", "--task", "fundamental", "--method", "magsac", "--data", f"{FOLD}/test.h5",
                          "--iterations", "1000", "--out-dir", "out"], ["out"]),
    "fold_eval_poselib": ([f"{FOLD}/test.h5", "params.yaml"],
                          ["evaluate", "--task", "fundamental", "--method", "poselib", "--data", f"{FOLD}/test.h5",
                           "--iterations", "1000", "--out-dir", "out"], ["out"]),
    "import_scene": (["data/strecha", "params.yaml"],
                     ["import-scenes", "--src", "data/strecha", "--out", "out/raw", "--scenes", "entry-P10",
                      "--max-features", "8000", "--min-matches", "100"], ["out"]),
}
SKIP_NAMES = ("timing.json",)  # wall times beside a result (results only are hashed)
SKIP_SUFFIXES = (".state.pt",)  # a training's resume state (holds its wall time; not an output of the record)


def tree_md5(paths: list[Path]) -> str:
    h = hashlib.md5()
    for top in paths:
        files = sorted(p for p in (top.rglob("*") if top.is_dir() else [top]) if p.is_file())
        for p in files:
            if p.name in SKIP_NAMES or p.name.endswith(SKIP_SUFFIXES):
                continue
            h.update(str(p.relative_to(top.parent)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()[:8]


def build_shim(where: Path) -> str:
    src, lib = where / "shim.c", where / "libmklintel.so"
    src.write_text("int mkl_serv_intel_cpu_true(void){return 1;}\n")
    subprocess.run(["gcc", "-shared", "-fPIC", "-o", str(lib), str(src)], check=True)
    return str(lib)


def run(workload: str, setting: dict, shim: str | None, tmp: Path) -> tuple[str, float]:
    inputs, argv, outs = WORKLOADS[workload]
    work = Path(tempfile.mkdtemp(dir=tmp))
    for rel in inputs:
        (work / rel).parent.mkdir(parents=True, exist_ok=True)
        (work / rel).symlink_to(ROOT / rel)
    env = {k: v for k, v in os.environ.items() if k not in PINNED and k != "LD_PRELOAD"}
    env.update({k: v for k, v in setting.items() if not k.startswith("@")})
    env[numerics.ENV] = setting.get("@mode", "native")  # every other row runs native, whatever the record's mode
    env.update(OMP_NUM_THREADS="1", MLFLOW_TRACKING_URI=f"sqlite:///{work}/mlflow.db", CI="true")
    if "@shim" in setting:
        env["LD_PRELOAD"] = shim
    t0 = time.perf_counter()
    r = subprocess.run([str(BIN / "rlsac"), *argv, "--no-tracking"], cwd=work, env=env, capture_output=True,
                       text=True)
    seconds = time.perf_counter() - t0
    if r.returncode:
        raise SystemExit(f"{workload}: rlsac exited {r.returncode}: {r.stderr.strip().splitlines()[-1:]}")
    digest = tree_md5([work / o for o in outs])
    shutil.rmtree(work)
    return digest, seconds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workloads", default=",".join(WORKLOADS))
    ap.add_argument("--settings", default=",".join(SETTINGS))
    ap.add_argument("--mkl-intel-shim", action="store_true", help="also the settings with MKL's Intel branch")
    args = ap.parse_args()
    names = [s for s in args.settings.split(",") if args.mkl_intel_shim or "@shim" not in SETTINGS[s]]
    with tempfile.TemporaryDirectory() as t:
        tmp = Path(t)
        shim = build_shim(tmp) if args.mkl_intel_shim else None
        print(f"{'workload':18} {'setting':20} {'md5':8} {'seconds':>8} {'ratio':>6}")
        for w in args.workloads.split(","):
            base = None
            for s in names:
                digest, sec = run(w, SETTINGS[s], shim, tmp)
                base = sec if base is None else base
                print(f"{w:18} {s:20} {digest:8} {sec:8.1f} {sec / base:6.2f}", flush=True)


if __name__ == "__main__":
    main()
