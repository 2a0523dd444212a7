"""The line experiment's data files: a synthetic line set from params.yaml ``lines_data`` (``rlsac synth-lines``) and
the files of one outlier rate from params.yaml ``lines`` (``rlsac lines-data``: data/lines/<split>_o<rate>.h5).

Below the commands that use them (rlsac.commands, the CLI) and the reports that regenerate a recorded file
(rlsac.reports.provenance): config, io, tracking and the generator (rlsac.data.lines) only.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rlsac import config
from rlsac.config import read_params, section
from rlsac.errors import RlsacError
from rlsac.io import check_writable
from rlsac.tracking import check_store, data_label, start_run


def line_conf(options: dict[str, Any], params_path: str | Path | None = "params.yaml"):
    """LineDataConf = defaults <- params.yaml ``lines_data`` <- ``options`` (None values ignored)."""
    from rlsac.data.lines import LineDataConf

    merged = {**section(read_params(params_path), "lines_data"), **{k: v for k, v in options.items() if v is not None}}
    conf = config.build(LineDataConf, merged, "lines_data")
    conf.check()
    return conf


def default_lines_path(conf) -> Path:
    return Path("data") / "lines" / f"lines_o{conf.outlier_rate:g}_s{conf.seed}.h5"


def synth_lines(options: dict[str, Any], track: bool = True, params_path: str | Path | None = "params.yaml") -> dict:
    """Generate a synthetic line set and write it atomically.

    options: LineDataConf fields (outlier_rate, n_instances, n_points, band, ..., seed) and ``out``.
    -> {"path", "conf", "n_instances", "n_points", "inlier_fraction", "run_id"}
    """
    from rlsac.data import lines

    options = dict(options)
    out = options.pop("out", None)
    conf = line_conf(options, params_path)
    path = check_writable(Path(out) if out else default_lines_path(conf))
    check_store(track, "lines")
    params = config.to_dict(conf)
    name = f"synth-lines {data_label(path)} o{conf.outlier_rate:g} s{conf.seed}"
    with start_run("lines", name, params={**params, "out": str(path)},
                   tags={"command": "synth-lines", "artifact_path": str(path)}, enabled=track) as run:
        data = lines.generate(conf)
        lines.write(path, data, conf)
        frac = float(data["inlier_mask"].mean())
        run.metrics({"inlier_fraction": frac})
    return {"path": str(path), "conf": params, "n_instances": conf.n_instances, "n_points": conf.n_points,
            "inlier_fraction": frac, "run_id": run.run_id}


def lines_protocol_data(options: dict[str, Any], track: bool = True,
                        params_path: str | Path | None = "params.yaml") -> dict:
    """The line experiment's files for one outlier rate (params.yaml ``lines``, used by dvc.yaml).

    options: rate (required), splits ("train,val,test"), out_dir ("data/lines"). Split s gets
    ``lines.n_<s>`` instances and seed ``lines.seed_<s> + round(10 * rate)``, in ``<out_dir>/<s>_o<rate>.h5``.
    -> {"files": [...], "seeds": {split: seed}}
    """
    if options.get("rate") is None:
        raise RlsacError("lines-data needs --rate")
    rate = config.check_value("rate", options["rate"], float, "[0, 1)")
    proto = section(read_params(params_path), "lines")
    splits = options.get("splits")
    splits = "train,val,test" if splits is None else splits  # --splits '' names none: an error, not all three
    splits = [x.strip() for x in splits.split(",") if x.strip()] if isinstance(splits, str) else list(splits)
    if not splits:
        raise RlsacError("lines-data --splits names no split")
    if len(set(splits)) != len(splits):
        raise RlsacError(f"lines-data --splits repeats a split: {','.join(splits)}")
    defaults = {"n_train": 4000, "n_val": 200, "n_test": 1000, "seed_train": 1000, "seed_val": 2000, "seed_test": 3000}
    plan = []
    for split in splits:  # every split checked (and its generator settings built) before anything is written
        if f"n_{split}" not in {**defaults, **proto} or f"seed_{split}" not in {**defaults, **proto}:
            raise RlsacError(f"unknown split {split!r}: params.yaml lines has no n_{split}/seed_{split}")
        n = config.check_value(f"lines.n_{split}", proto.get(f"n_{split}", defaults.get(f"n_{split}")), int,
                               "[1, inf)")
        seed = config.check_value(f"lines.seed_{split}", proto.get(f"seed_{split}", defaults.get(f"seed_{split}")),
                                  int, "[0, inf)") + round(10 * rate)
        out = check_writable(Path(options.get("out_dir") or "data/lines") / f"{split}_o{rate:g}.h5")
        line_conf({"outlier_rate": rate, "n_instances": n, "seed": seed}, params_path)
        plan.append((split, n, seed, out))
    check_store(track, "lines")
    files, seeds = [], {}
    for split, n, seed, out in plan:
        s = synth_lines({"outlier_rate": rate, "n_instances": n, "seed": seed, "out": str(out)}, track, params_path)
        files.append(s["path"])
        seeds[split] = seed
    return {"files": files, "seeds": seeds}
