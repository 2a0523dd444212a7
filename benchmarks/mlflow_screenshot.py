"""What a user sees when they open the MLflow UI on this project's runs (issue #47, item 4): a headless screenshot.

Makes a fresh sqlite store with two real `rlsac evaluate` runs (uniform and RANSAC on a small line file), starts
`mlflow server` on 127.0.0.1, and has headless Chromium (Debian's `chromium`; `apt-get install chromium`) take a
screenshot of the experiment's page through the link docs/tracking.md gives (the model-training workflow and the
experiment's shared view `rlsac`, which rlsac.tracking writes: the main metrics as columns, sorted by mAA); prints
the PNG's path and whether the page shows the runs table with the mAA column, sorted by mAA, rather than MLflow 3's
GenAI overview. Everything stays on this machine (loopback only) and the server is stopped at the end.

    python benchmarks/mlflow_screenshot.py --out /tmp/mlflow_runs.png
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from rlsac.tracking import mlflow_server


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="/tmp/mlflow_runs.png")
    a = ap.parse_args()
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        print("error: no chromium on PATH (apt-get install chromium)", file=sys.stderr)
        return 2
    work = Path(tempfile.mkdtemp(prefix="rlsac-mlflow-"))
    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{work / 'mlflow.db'}"}
    bin_dir = Path(sys.executable).parent
    run = lambda *args: subprocess.run([str(bin_dir / "rlsac"), *args], cwd=work, env=env, check=True,  # noqa: E731
                                       capture_output=True)
    run("synth-lines", "--outlier", "0.5", "--n-instances", "20", "--out", "l.h5")
    for method in ("uniform", "ransac"):
        run("evaluate", "--task", "line", "--method", method, "--data", "l.h5", "--iterations", "50")
    try:
        with mlflow_server(env["MLFLOW_TRACKING_URI"], work) as base:
            import mlflow

            mlflow.set_tracking_uri(base)
            exp = mlflow.get_experiment_by_name("lines")
            # MLflow 3 opens on its GenAI pages unless asked for the model-training workflow (a URL parameter, then
            # remembered by the browser): the link the docs give
            url = (f"{base}/#/experiments/{exp.experiment_id}/runs"
                   "?workflowType=machine_learning&viewStateShareKey=rlsac")
            subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                            "--window-size=2800,900", "--virtual-time-budget=15000", f"--screenshot={a.out}", url],
                           check=True, capture_output=True, timeout=120)
            dom = subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu",
                                  "--virtual-time-budget=15000", "--dump-dom", url],
                                 check=True, capture_output=True, timeout=120, text=True).stdout
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(f"screenshot: {a.out} ({url})")
    print(f"runs table shown: {'Run Name' in dom or 'Run name' in dom}; GenAI overview: {'Token Usage' in dom}; "
          f"sorted by mAA: {'Sort: mAA' in dom}; metric columns: {'>Metrics<' in dom and '>mAA<' in dom}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
