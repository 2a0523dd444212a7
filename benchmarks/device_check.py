"""The ``--device cuda`` paths, run end to end on a machine with a GPU (the tests never need one: CI has none).

Two checks, each made of two steps (the data here, where the full data is; the run on the GPU machine):

    python benchmarks/device_check.py make-data --out .devcheck         # small h5 subsets of the real data
    python benchmarks/device_check.py run --data .devcheck --out OUT    # every path on cuda and cpu (below)
    python benchmarks/device_check.py make-speed-data --out .devcheck   # full-size test files, committed models
    python benchmarks/device_check.py speed --data .devcheck --out OUT  # wall time at the recipes' sizes

Results: reports/device.md.

``run`` calls the CLI (``python -c "from rlsac.cli import main; main()" ...``, no MLflow) for every torch command,
on cuda and on cpu side by side, and checks:

- ``train`` (RLSAC on lines, F and E; NG-RANSAC on F) exits 0 on cuda and its checkpoint loads on cpu;
- ``evaluate`` of one checkpoint on cuda and on cpu: every summary finite; the mAA gap between the two devices
  beside the gap between two cpu seeds (the same seed draws other numbers on cuda: MAX_GAP);
- a cpu-trained checkpoint evaluates on cuda and a cuda-trained one on cpu;
- ``train --resume`` on cuda after a SIGTERM finishes at the full step count; cuda's state on cpu is refused with
  one ``error:`` line naming the device, exit 2;
- ``plot`` with device=cuda writes its figure;
- ``select`` (the checkpoint-selection replay) and ``calibrate-lines`` run on cuda.

It prints one line per job (exit code, wall seconds, mAA) and the cuda/cpu wall-time ratio per command, both
arms measured in this run on the same machine, each process on one CPU thread. Exit status 1 if a check fails.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

CLI = [sys.executable, "-c", "from rlsac.cli import main; main()"]
# cuda's generator (Philox) draws other numbers than the CPU's (Mersenne twister) from the same seed, so an
# evaluation on cuda is another draw of the same distribution: its gap to cpu is printed beside the gap between two
# cpu seeds. Only a gap no draw explains fails (a broken path scores far lower, as a sampler ignoring its network)
MAX_GAP = 0.15


def _head(src_path: str, dst_path: Path, n: int) -> None:
    """The first ``n`` rows of every dataset of an h5 file, its attributes kept (n_pairs, if any, counted again)."""
    import h5py

    with h5py.File(src_path) as src, h5py.File(dst_path, "w") as dst:
        for key, ds in src.items():
            dst[key] = ds[:n]
        for k, v in src.attrs.items():
            dst.attrs[k] = v
        if "n_pairs" in src.attrs:
            dst.attrs["n_pairs"] = min(n, len(src["coords"]))


def make_data(out: Path, pairs: tuple[int, int, int]) -> None:
    """The first ``pairs`` (train, val, test) pairs of the hard entry fold and the first 400 / 100 / 200 lines
    at outlier rate 0.7, as h5 files in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    sources = {"fold": ("data/folds/hard/entry/{}.h5", pairs), "lines": ("data/lines/{}_o0.7.h5", (400, 100, 200))}
    for name, (pattern, counts) in sources.items():
        for split, n in zip(("train", "val", "test"), counts, strict=True):
            _head(pattern.format(split), out / f"{name}_{split}.h5", n)
            print(f"wrote {out / f'{name}_{split}.h5'}")


def make_speed_data(out: Path, pairs: int) -> None:
    """For ``speed``: the whole 0.7 line test file, the first ``pairs`` test pairs of the hard castle fold, and the
    committed models that evaluate them (the 0.7 line model, castle's RLSAC seed 1)."""
    import shutil

    out.mkdir(parents=True, exist_ok=True)
    shutil.copy("data/lines/test_o0.7.h5", out / "speed_lines_test.h5")
    _head("data/folds/hard/castle/test.h5", out / "speed_fold_test.h5", pairs)
    shutil.copy("checkpoints/line_o0.7.pt", out / "speed_line.pt")
    shutil.copy("checkpoints/folds/hard/castle/rlsac-s1.pt", out / "speed_fold.pt")
    print(f"wrote the speed files into {out}")


def main_speed(data: Path, out: Path, device: str) -> int:
    """Wall time of the recipes' sizes on ``device`` and on cpu (one CPU thread), each arm alone on its core(s):
    a training step with the line / F recipe's batch (num_envs, batch_size), and evaluation of committed models on
    1000 lines and on many castle pairs at the paper's budgets."""
    out.mkdir(parents=True, exist_ok=True)
    logs = out / "logs"
    logs.mkdir(exist_ok=True)
    line_rec = {"threads": 1, "val_instances": 50, "val_every": 100, "ckpt_every": 1000, "sac.total_steps": 200,
                "sac.num_envs": 32, "sac.batch_size": 64, "sac.learning_starts": 64}
    f_rec = {"threads": 1, "val_instances": 8, "val_iterations": 50, "val_every": 100, "ckpt_every": 1000,
             "sac.total_steps": 100, "sac.num_envs": 16, "sac.batch_size": 32, "sac.learning_starts": 32}
    jobs = []
    for dev in (device, "cpu"):
        jobs.append((("train line recipe, 200 steps", dev),
                     train_argv("line", "rlsac", data, out / f"l-{dev}.pt", dev, line_rec)))
        jobs.append((("train F recipe, 100 steps", dev),
                     train_argv("fundamental", "rlsac", data, out / f"f-{dev}.pt", dev, f_rec)))
        for bs in (256, 1000):
            jobs.append(((f"evaluate lines 1000 x 150 it, batch {bs}", dev),
                         ["evaluate", "--task", "line", "--method", "rlsac", "--checkpoint",
                          str(data / "speed_line.pt"), "--data", str(data / "speed_lines_test.h5"),
                          "--iterations", "150", "--batch-size", str(bs),
                          "--device", dev, "--out-dir", str(out / f"el-{bs}-{dev}"), "--no-tracking"] + PARAMS))
        jobs.append((("evaluate F castle pairs x 1000 it", dev),
                     ["evaluate", "--task", "fundamental", "--method", "rlsac", "--checkpoint",
                      str(data / "speed_fold.pt"), "--data", str(data / "speed_fold_test.h5"), "--iterations", "1000",
                      "--device", dev, "--out-dir", str(out / f"ef-{dev}"), "--no-tracking"] + PARAMS))
    def do(job):
        return job[0], run_cli(job[1], logs / ("-".join(job[0]).replace(" ", "_").replace(",", "") + ".log"))

    # the GPU's jobs one at a time (alone on the GPU), the CPU's side by side (one core each)
    with ThreadPoolExecutor(1) as gpu, ThreadPoolExecutor(len(jobs)) as cpu:
        futures = [(gpu if j[0][1] == device and device != "cpu" else cpu).submit(do, j) for j in jobs]
        done = dict(f.result() for f in futures)
    failed = 0
    print(f"\n{'':45s} {device:>9s} {'cpu':>9s}  ratio   mAA {device} / cpu")
    for (what, dev), _ in jobs:
        if dev != device:
            continue
        (rc, wall, last), (rc2, wall2, last2) = done[(what, dev)], done[(what, "cpu")]
        failed += rc != 0 or rc2 != 0
        sums = [summary(out / d) for d in _eval_dirs(what, dev)] if what.startswith("evaluate") else []
        maa = " / ".join(f"{x['mAA']:.3f}" if x else "-" for x in sums)
        print(f"{what:45s} {wall:8.1f}s {wall2:8.1f}s  {wall / wall2:5.2f}   {maa} {last or ''} {last2 or ''}")
    return 1 if failed else 0


def _eval_dirs(what: str, dev: str) -> list[str]:
    if "lines" in what:
        bs = what.rsplit(" ", 1)[1]
        return [f"el-{bs}-{dev}", f"el-{bs}-cpu"]
    return [f"ef-{dev}", "ef-cpu"]


class Checks:
    def __init__(self):
        self.failed: list[str] = []

    def expect(self, ok: bool, what: str) -> None:
        print(("ok    " if ok else "FAIL  ") + what, flush=True)
        if not ok:
            self.failed.append(what)


def run_cli(argv: list[str], log: Path, env_extra: dict | None = None) -> tuple[int, float, str]:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", **(env_extra or {})}
    t0 = time.perf_counter()
    p = subprocess.run(CLI + argv, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    log.write_text(" ".join(argv) + "\n--- stdout\n" + p.stdout + "\n--- stderr\n" + p.stderr)
    return p.returncode, wall, p.stderr.strip().splitlines()[-1] if p.stderr.strip() else ""


PARAMS = ["--params", "params.yaml"]


def train_argv(task: str, method: str, data: Path, out: Path, device: str, sets: dict) -> list[str]:
    prefix = "lines" if task == "line" else "fold"
    argv = ["train", "--task", task, "--method", method, "--data", str(data / f"{prefix}_train.h5"),
            "--val-data", str(data / f"{prefix}_val.h5"), "--out", str(out), "--device", device, "--seed", "0",
            "--no-tracking"] + PARAMS
    for k, v in sets.items():
        argv += ["--set", f"{k}={v}"]
    return argv


# short recipes: the point is that every path runs on cuda, not a trained model
RLSAC_SETS = {"line": {"threads": 1, "val_instances": 50, "val_every": 50, "ckpt_every": 50, "sac.total_steps": 150,
                       "sac.num_envs": 16, "sac.batch_size": 32, "sac.learning_starts": 64},
              "fundamental": {"threads": 1, "val_instances": 8, "val_iterations": 50, "val_every": 50,
                              "ckpt_every": 50, "sac.total_steps": 100, "sac.num_envs": 8, "sac.batch_size": 16,
                              "sac.learning_starts": 32},
              "essential": {"threads": 1, "val_instances": 8, "val_iterations": 50, "val_every": 50,
                            "ckpt_every": 50, "sac.total_steps": 100, "sac.num_envs": 8, "sac.batch_size": 16,
                            "sac.learning_starts": 32}}
NG_SETS = {"threads": 1, "val_instances": 8, "val_iterations": 50, "val_every": 50, "ckpt_every": 50,
           "ngransac.steps": 100}


def summary(out_dir: Path) -> dict | None:
    from rlsac.reports.tables import read_summary

    return read_summary(out_dir / "summary.json")


def main_run(data: Path, out: Path, device: str, workers: int, iterations: dict) -> int:
    out.mkdir(parents=True, exist_ok=True)
    logs = out / "logs"
    logs.mkdir(exist_ok=True)
    checks = Checks()
    import torch

    print(f"torch {torch.__version__}, cuda available: {torch.cuda.is_available()}"
          + (f", {torch.cuda.get_device_name(0)}" if torch.cuda.is_available() else ""), flush=True)
    checks.expect(device != "cuda" or torch.cuda.is_available(), "torch sees a GPU")

    models = [("line", "rlsac"), ("fundamental", "rlsac"), ("fundamental", "ngransac"), ("essential", "rlsac")]
    train_jobs = []
    for task, method in models:
        sets = NG_SETS if method == "ngransac" else RLSAC_SETS[task]
        for dev in (device, "cpu"):
            ck = out / "ck" / f"{task}-{method}-{dev}.pt"
            train_jobs.append(((task, method, dev), train_argv(task, method, data, ck, dev, sets), ck))

    def do(job):
        key, argv, _ = job
        return key, run_cli(argv, logs / ("-".join(key) + ".log"))

    with ThreadPoolExecutor(workers) as pool:
        trained = dict(pool.map(do, train_jobs))
    walls = {}
    for (key, _, ck) in train_jobs:
        rc, wall, last = trained[key]
        walls[("train",) + key] = wall
        checks.expect(rc == 0 and ck.is_file(), f"train {' '.join(key)}: exit {rc}, {wall:.1f} s {last}")
        if rc == 0:
            from rlsac.rl.checkpoint import load_actor

            try:
                load_actor(ck, "cpu", kind="ngransac" if key[1] == "ngransac" else "rlsac")
                checks.expect(True, f"  checkpoint of {' '.join(key)} loads on cpu")
            except Exception as e:  # noqa: BLE001 - reported, not raised
                checks.expect(False, f"  checkpoint of {' '.join(key)} loads on cpu: {e}")

    # evaluate: each checkpoint on both devices; the untrained samplers (uniform, guided) on both
    eval_jobs = []
    for task, method in models:
        prefix = "lines" if task == "line" else "fold"
        for ck_dev in (device, "cpu"):
            ck = out / "ck" / f"{task}-{method}-{ck_dev}.pt"
            for dev in (device, "cpu"):
                key = (task, method, f"ckpt-{ck_dev}", dev)
                argv = ["evaluate", "--task", task, "--method", method, "--checkpoint", str(ck), "--data",
                        str(data / f"{prefix}_test.h5"), "--iterations", str(iterations[task]), "--device", dev,
                        "--out-dir", str(out / "eval" / "-".join(key)), "--no-tracking"] + PARAMS
                eval_jobs.append((key, argv, None))
    for key, argv, _ in list(eval_jobs):  # the seed-to-seed gap on cpu: the scale of a draw
        if key[3] == "cpu":
            key2 = key[:3] + ("cpu-seed1",)
            argv2 = argv[:argv.index("--out-dir")] + ["--seed", "1", "--out-dir", str(out / "eval" / "-".join(key2)),
                                                      "--no-tracking"] + PARAMS
            eval_jobs.append((key2, argv2, None))
    for task, method in (("fundamental", "guided"), ("fundamental", "uniform"), ("fundamental", "rlsac-lo")):
        for dev in (device, "cpu"):
            key = (task, method, "-", dev)
            argv = ["evaluate", "--task", task, "--method", method, "--data", str(data / "fold_test.h5"),
                    "--iterations", str(iterations[task]), "--device", dev,
                    "--out-dir", str(out / "eval" / "-".join(key)), "--no-tracking"] + PARAMS
            if method == "rlsac-lo":
                argv += ["--checkpoint", str(out / "ck" / f"fundamental-rlsac-{device}.pt")]
            eval_jobs.append((key, argv, None))
    with ThreadPoolExecutor(workers) as pool:
        evaluated = dict(pool.map(do, eval_jobs))
    maa = {}
    for key, _, _ in eval_jobs:
        rc, wall, last = evaluated[key]
        walls[("evaluate",) + key] = wall
        s = summary(out / "eval" / "-".join(key))
        finite = s is not None and all(math.isfinite(float(s[k])) for k in ("mAA", "median_R" if key[0] != "line"
                                                                              else "mAA"))
        maa[key] = s["mAA"] if s else None
        checks.expect(rc == 0 and finite, f"evaluate {' '.join(key)}: exit {rc}, {wall:.1f} s, mAA {maa[key]} {last}")
    for key in eval_jobs:
        k = key[0]
        if k[3] != device:
            continue
        other, seed1 = k[:3] + ("cpu",), k[:3] + ("cpu-seed1",)
        if maa.get(k) is not None and maa.get(other) is not None:
            gap = abs(maa[k] - maa[other])
            ref = f", cpu seed 1 - seed 0: {maa[seed1] - maa[other]:+.4f}" if maa.get(seed1) is not None else ""
            checks.expect(gap <= MAX_GAP, f"  {' '.join(k[:3])}: mAA {device} {maa[k]:.4f} vs cpu {maa[other]:.4f} "
                                          f"(gap {gap:.4f}, at most {MAX_GAP}{ref})")

    resume_check(checks, data, out, device, logs)
    select_check(checks, data, out, device, logs, iterations["line"])
    calibrate_check(checks, out, device, logs)
    plot_check(checks, data, out, device, logs)

    print("\nwall time, cuda / cpu (one CPU thread each, both measured here):", flush=True)
    for key, wall in sorted(walls.items()):
        if key[-1] == device and device != "cpu":
            ref = walls.get(key[:-1] + ("cpu",))
            if ref:
                print(f"  {' '.join(key[:-1]):55s} {wall:7.1f} s / {ref:7.1f} s = {wall / ref:5.2f}")
    (out / "walls.json").write_text(json.dumps({" ".join(k): v for k, v in walls.items()}, indent=1))
    print(f"\n{len(checks.failed)} failed: {checks.failed}" if checks.failed else "\nall checks passed")
    return 1 if checks.failed else 0


def resume_check(checks: Checks, data: Path, out: Path, device: str, logs: Path) -> None:
    """SIGTERM once the first state file is written, then --resume: exit 0 and the full step count."""
    import torch

    sets = {**RLSAC_SETS["line"], "sac.total_steps": 400}
    ck = out / "resume" / "m.pt"
    argv = train_argv("line", "rlsac", data, ck, device, sets)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    whole_ck = out / "resume-whole" / "m.pt"  # the same run uninterrupted, beside it: is the resume exact there?
    whole_log = open(logs / "resume-whole.log", "w")  # noqa: SIM115 - closed once the run ends, below
    whole = subprocess.Popen(CLI + train_argv("line", "rlsac", data, whole_ck, device, sets),
                             stdout=whole_log, stderr=subprocess.STDOUT, env=env)
    with open(logs / "resume-first.log", "w") as log:
        p = subprocess.Popen(CLI + argv, stdout=log, stderr=subprocess.STDOUT, env=env)
        state = ck.with_suffix(".state.pt")
        while p.poll() is None and not state.is_file():
            time.sleep(0.2)
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
        rc = p.wait()
    checks.expect(rc == 128 + signal.SIGTERM, f"resume: first run stopped by SIGTERM (exit {rc})")
    stopped = torch.load(state, weights_only=False, map_location="cpu")["step"] if state.is_file() else None
    rc, wall, last = run_cli(argv + ["--resume"], logs / "resume-second.log")
    final = torch.load(state, weights_only=False, map_location="cpu")["step"] if state.is_file() else None
    checks.expect(rc == 0 and final == 400, f"resume on {device}: stopped at {stopped}, resumed to {final}, exit {rc}")
    whole_rc = whole.wait()
    whole_log.close()
    if whole_rc == 0 and rc == 0:
        a = torch.load(state, weights_only=False, map_location="cpu")["agent"]
        b = torch.load(whole_ck.with_suffix(".state.pt"), weights_only=False, map_location="cpu")["agent"]
        same = all(torch.equal(a[k], b[k]) for k in a)
        print(f"info  resumed = uninterrupted final agent on {device}: {same} (bit-exact is promised on cpu only)")
    # the state of a cuda run resumed on cpu: works, or one error line with exit 2 (never a traceback)
    import shutil

    ck2 = out / "resume-cpu" / "m.pt"
    ck2.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(state, ck2.with_suffix(".state.pt"))
    if ck.is_file():
        shutil.copy(ck, ck2)
    sets2 = {**sets, "sac.total_steps": 450}
    rc, wall, last = run_cli(train_argv("line", "rlsac", data, ck2, "cpu", sets2) + ["--resume"],
                             logs / "resume-cross.log")
    text = (logs / "resume-cross.log").read_text()
    expected = rc == 0 if device == "cpu" else (rc == 2 and last.endswith(f"resume it with --device {device}"))
    checks.expect(expected and "Traceback" not in text, f"resume of a {device} state on cpu: exit {rc} {last}")


def select_check(checks: Checks, data: Path, out: Path, device: str, logs: Path, iterations: int) -> None:
    """``rlsac select`` replays a line model's training on each device and tests every validated actor. The replay
    must give the kept actor's committed mAA: exact on cpu; on cuda, where training is not bit-exact, either the
    same or one error line that says the replay differs (never a wrong table)."""
    for dev in (device, "cpu"):
        ck = out / "ck" / f"line-rlsac-{dev}.pt"
        argv = ["select", "--checkpoint", str(ck), "--data", str(data / "lines_test.h5"), "--kept-eval",
                str(out / "eval" / f"line-rlsac-ckpt-{dev}-{dev}"), "--out", str(out / "select" / f"line-{dev}"),
                "--iterations", str(iterations), "--device", dev, "--no-tracking"] + PARAMS
        rc, wall, last = run_cli(argv, logs / f"select-{dev}.log")
        text = (logs / f"select-{dev}.log").read_text()
        wrote = (out / "select" / f"line-{dev}.csv").is_file()
        ok = (rc == 0 and wrote) or (dev != "cpu" and rc == 2 and last.startswith("error:") and not wrote)
        checks.expect(ok and "Traceback" not in text, f"select on {dev}: exit {rc}, {wall:.1f} s, wrote {wrote} {last}")


def calibrate_check(checks: Checks, out: Path, device: str, logs: Path) -> None:
    """``rlsac calibrate-lines`` (the line calibration, our RANSAC on fresh lines) on both devices."""
    rows = {}
    for dev in (device, "cpu"):
        stem = out / "calibrate" / f"cal-{dev}"
        argv = ["calibrate-lines", "--n-instances", "200", "--n-seeds", "2", "--out", str(stem), "--device", dev,
                "--no-tracking"] + PARAMS
        rc, wall, last = run_cli(argv, logs / f"calibrate-{dev}.log")
        rows[dev] = stem.with_suffix(".csv").read_text() if stem.with_suffix(".csv").is_file() else None
        checks.expect(rc == 0 and rows[dev] is not None, f"calibrate-lines on {dev}: exit {rc}, {wall:.1f} s {last}")
    if device != "cpu" and all(rows.values()):
        print(f"info  calibrate-lines csv, {device}:\n{rows[device]}info  cpu:\n{rows['cpu']}")


def plot_check(checks: Checks, data: Path, out: Path, device: str, logs: Path) -> None:
    d = out / "plot"
    argv = ["plot", "--set", "which=line", "--set", f"device={device}", "--set", f"line_data={data / 'lines_test.h5'}",
            "--set", f"line_checkpoint={out / 'ck' / f'line-rlsac-{device}.pt'}", "--set", f"out_dir={d}",
            "--no-tracking"]
    rc, wall, last = run_cli(argv, logs / "plot.log")
    pngs = sorted(d.glob("*.png")) if d.is_dir() else []
    checks.expect(rc == 0 and bool(pngs), f"plot which=line device={device}: exit {rc}, {[p.name for p in pngs]} "
                                          f"{last}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("make-data")
    m.add_argument("--out", type=Path, default=Path(".devcheck"))
    m.add_argument("--pairs", type=int, nargs=3, default=(48, 16, 24), metavar=("TRAIN", "VAL", "TEST"))
    ms = sub.add_parser("make-speed-data")
    ms.add_argument("--out", type=Path, default=Path(".devcheck"))
    ms.add_argument("--pairs", type=int, default=160)
    sp = sub.add_parser("speed")
    sp.add_argument("--data", type=Path, default=Path(".devcheck"))
    sp.add_argument("--out", type=Path, required=True)
    sp.add_argument("--device", default="cuda")
    sp.add_argument("--params", default="params.yaml")
    r = sub.add_parser("run")
    r.add_argument("--data", type=Path, default=Path(".devcheck"))
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--device", default="cuda", help="the arm compared with cpu (cpu here: a dry run of the script)")
    r.add_argument("--workers", type=int, default=8, help="jobs at a time (each on one CPU thread)")
    r.add_argument("--params", default="params.yaml", help="the params file of train and evaluate")
    r.add_argument("--iterations", type=int, nargs=3, default=(150, 1000, 1000), metavar=("LINE", "F", "E"))
    a = ap.parse_args()
    if a.cmd == "make-data":
        make_data(a.out, tuple(a.pairs))
    elif a.cmd == "make-speed-data":
        make_speed_data(a.out, a.pairs)
    elif a.cmd == "speed":
        PARAMS[1] = a.params
        sys.exit(main_speed(a.data, a.out, a.device))
    else:
        PARAMS[1] = a.params
        sys.exit(main_run(a.data, a.out, a.device, a.workers, dict(zip(("line", "fundamental", "essential"),
                                                                        a.iterations, strict=True))))


if __name__ == "__main__":
    main()
