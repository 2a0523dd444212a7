"""Per-stage overhead of ``rlsac pipeline``: the direct runner against ``dvc repro -s`` per stage (issue #50, item 1).

    python benchmarks/pipeline_overhead.py                   # 20 trivial stages, a lock of their entries only
    python benchmarks/pipeline_overhead.py --pad 1244        # the lock padded to the paper profile's size (~1.5 MB)
    python benchmarks/pipeline_overhead.py --stages 40 --workers 2

Builds a toy git + DVC repository in a temporary folder: ``--stages`` independent stages whose command is
``echo`` (so nearly all of a stage's time is the runner's own), and with ``--pad N`` N more entries in dvc.lock
(stages no longer in dvc.yaml, about 1.2 kB each as the paper profile's are: DVC reads and writes them all for each
stage). Then, on one local Ray cluster started once, each runner runs the stages on a fresh copy, ``--repeat``
times (the best wall time counts); the per-stage overhead is the pipeline's wall time (Ray's start excluded) divided
by the stage count, times the worker count. Prints both and their ratio (dvc / direct), measured in this run, and
whether both runners' dvc.lock hold the same entries (the dvc runner appends them as stages end, so their order
differs; tests/test_ray_pipeline.py checks the direct runner's bytes against a serial `dvc repro`'s).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _md5(text: str) -> str:
    import hashlib

    return hashlib.md5(text.encode()).hexdigest()


def _pad_entry(i: int) -> str:
    deps = "".join(f"    - path: data/pad/{i}/in{k}.h5\n      hash: md5\n      md5: {_md5(f'{i}-{k}')}\n"
                   f"      size: {1000 + k}\n" for k in range(8))
    return (f"  padded@{i}:\n    cmd: rlsac evaluate --task line --data data/pad/{i}/in.h5 --out-dir "
            f"reports/pad/{i}\n    deps:\n{deps}    outs:\n    - path: reports/pad/{i}\n      hash: md5\n"
            f"      md5: {_md5(str(i))}.dir\n      size: 4096\n      nfiles: 3\n")


def make_repo(path: Path, n_stages: int, pad: int) -> Path:
    import yaml

    env = {**os.environ, "PATH": str(Path(sys.executable).parent) + os.pathsep + os.environ.get("PATH", "")}
    path.mkdir(parents=True)
    subprocess.run(["git", "init", "-q"], cwd=path, check=True)
    subprocess.run([sys.executable, "-m", "dvc", "init", "-q"], cwd=path, check=True, env=env)
    stages = {"s": {"foreach": list(range(n_stages)), "do": {"cmd": "echo ${item} > out/s${item}.txt",
                                                             "outs": [{"out/s${item}.txt": {"cache": False}}]}}}
    (path / "dvc.yaml").write_text(yaml.safe_dump({"stages": stages}, sort_keys=False))
    (path / "out").mkdir()
    if pad:
        (path / "dvc.lock").write_text("schema: '2.0'\nstages:\n" + "".join(_pad_entry(i) for i in range(pad)))
    return path


def run_once(template: Path, work: Path, runner: str, workers: int) -> tuple[float, dict]:
    from rlsac.runners.pipeline import pipeline

    repo = work / runner
    shutil.rmtree(repo, ignore_errors=True)
    shutil.copytree(template, repo, symlinks=True)
    s = pipeline({"repo": str(repo), "runner": runner, "workers": workers}, track=False)
    if s["counts"]["done"] != len(s["todo"]):
        raise SystemExit(f"{runner}: {s['counts']}")
    import yaml

    return s["wall_s"], yaml.safe_load((repo / "dvc.lock").read_text())


def measure(n_stages: int, pad: int, workers: int = 1, repeat: int = 2, runners=("dvc", "direct"),
            report=print) -> dict:
    """Each runner's wall time (best of ``repeat``) and seconds per stage on ``n_stages`` echo stages with ``pad``
    extra lock entries, on a local Ray cluster of ``workers`` CPUs started once. -> {"best" {runner: s}, "per_stage"
    {runner: s}, "lock_bytes", "same_entries" (both runners' locks hold the same entries; None with one runner)}."""
    import ray

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    ray.init(address="local", num_cpus=workers, include_dashboard=False, log_to_driver=False)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            template = make_repo(Path(tmp) / "template", n_stages, pad)
            size = (template / "dvc.lock").stat().st_size if pad else 0
            best: dict[str, float] = {}
            locks: dict[str, dict] = {}
            for _ in range(repeat):
                for runner in runners:
                    t0 = time.perf_counter()
                    wall, locks[runner] = run_once(template, Path(tmp), runner, workers)
                    best[runner] = min(best.get(runner, float("inf")), wall)
                    report(f"  {runner:<6} {wall:7.2f} s ({time.perf_counter() - t0:.2f} s with planning)")
    finally:
        ray.shutdown()
    same = locks["dvc"] == locks["direct"] if len(locks) == 2 else None
    return {"best": best, "per_stage": {k: v * workers / n_stages for k, v in best.items()}, "lock_bytes": size,
            "same_entries": same}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--stages", type=int, default=20)
    p.add_argument("--pad", type=int, default=0, help="extra dvc.lock entries (the paper profile has 1244)")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--repeat", type=int, default=2)
    a = p.parse_args(argv)
    m = measure(a.stages, a.pad, a.workers, a.repeat, report=lambda line: print(line, flush=True))
    best, per = m["best"], m["per_stage"]
    print(f"{a.stages} stages, {a.workers} worker(s), dvc.lock padded with {a.pad} entries "
          f"({m['lock_bytes'] / 1e6:.2f} MB); best of {a.repeat}")
    for k in ("dvc", "direct"):
        print(f"{k:<6} runner: {best[k]:7.2f} s wall, {per[k]:.3f} s per stage")
    print(f"ratio dvc / direct: {per['dvc'] / per['direct']:.1f}x; same dvc.lock entries: "
          f"{'yes' if m['same_entries'] else 'NO'}")


if __name__ == "__main__":
    main()
