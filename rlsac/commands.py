"""Library entry points behind the ``rlsac`` commands that have no module of their own.

Each function takes a plain options dict (what the CLI parsed, or what a notebook passes) and a
``track`` flag, and returns a small summary dict; the CLI only prints it.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from rlsac import config
from rlsac.config import deep_update, parse_sets, read_params, section

# the line data commands' library (rlsac.data.line_files), re-exported: the CLI calls them through this module
from rlsac.data.line_files import default_lines_path, line_conf, lines_protocol_data, synth_lines  # noqa: F401
from rlsac.errors import RlsacError
from rlsac.io import atomic_path, check_writable, write_text
from rlsac.tracking import check_store, start_run

# Table 1 of the paper, RANSAC row: outlier rate -> (mAA@0.5 deg, median error in deg).
PAPER_RANSAC_LINES = {
    0.1: (0.870, 0.049), 0.2: (0.863, 0.052), 0.3: (0.850, 0.056), 0.4: (0.829, 0.061),
    0.5: (0.796, 0.071), 0.6: (0.746, 0.087), 0.7: (0.608, 0.135),
}


def check_lines_data(params: dict[str, Any]) -> None:
    """params.yaml ``lines_data``: LineDataConf fields (typed, ranged)."""
    from rlsac.data.lines import LineDataConf

    config.build(LineDataConf, section(params, "lines_data"), "lines_data")


def check_lines(params: dict[str, Any]) -> None:
    """params.yaml ``lines``, the line experiment's protocol: rates in [0, 1), iterations, per split ``n_<split>``
    instances and ``seed_<split>`` (``lines_protocol_data``), and the seed grid (issue #27): the other training
    ``seeds`` (from 1: seed 0 is each rate's model) of the models at ``seed_rates`` (rates of ``rates``), and
    NG-RANSAC's line recipe (issue #29): ``ngransac`` (NGRansacConf fields) and ``ngransac_val_every``; the tie of
    ``rlsac select`` on the line models (``select_tie``)."""
    from rlsac.rl.ngransac import NGRansacConf

    lines = section(params, "lines")
    for key, value in lines.items():
        if key == "ngransac":
            config.build(NGRansacConf, value, "lines.ngransac")
        elif key == "ngransac_val_every":
            config.check_value("lines.ngransac_val_every", value, int, "[1, inf)")
        elif key == "select_tie":
            config.check_value("lines.select_tie", value, float, "[0, inf)")
        elif key in ("rates", "seed_rates"):
            config.check_value(f"lines.{key}", value, list[float], "[0, 1)")
        elif key == "seeds":
            config.check_value("lines.seeds", value, list[int], "[1, 4294967295]")
        elif key in ("iterations",) or key.startswith("n_"):
            config.check_value(f"lines.{key}", value, int, "[1, inf)")
        elif key.startswith("seed_"):
            config.check_value(f"lines.{key}", value, int, config.SEED_RANGE)
        else:
            raise RlsacError(f"unknown params key lines.{key}; known: rates, iterations, n_<split>, seed_<split>, "
                             "seeds, seed_rates, select_tie, ngransac, ngransac_val_every")
    extra = sorted(set(lines.get("seed_rates", [])) - set(lines["rates"])) if "rates" in lines else []
    if extra:
        raise RlsacError(f"lines.seed_rates {extra} are not in lines.rates")


def check_calibration(params: dict[str, Any]) -> None:
    """params.yaml ``calibration``, the calibrate_lines stage's sizes: n_instances, n_seeds and the first seed."""
    ranges = {"n_instances": "[1, inf)", "n_seeds": "[1, inf)", "seed": config.SEED_RANGE}
    for key, value in section(params, "calibration").items():
        if key not in ranges:
            raise RlsacError(f"unknown params key calibration.{key}; known: {', '.join(ranges)}")
        config.check_value(f"calibration.{key}", value, int, ranges[key])


def calibration_table(ours: dict[float, tuple[float, float]],
                      paper: dict[float, tuple[float, float]] = PAPER_RANSAC_LINES,
                      oracle: dict[float, tuple[float, float]] | None = None,
                      per_seed: dict[float, list[float]] | None = None, band: float = 0.03) -> pd.DataFrame:
    """Side by side: ours vs the paper's (mAA, median) per outlier rate, with the differences (ours - paper),
    and, where given, the oracle (refinement on the true inliers) on the same instances and the spread of
    our mAA over seeds (sd, min, max, fraction of seeds whose mAA lies within ``band`` of the paper's)."""
    rows = []
    for rate in sorted(ours):
        o_maa, o_med = ours[rate]
        p_maa, p_med = paper.get(rate, (np.nan, np.nan))
        row = {"outlier_rate": rate, "mAA_ours": o_maa, "mAA_paper": p_maa, "mAA_diff": o_maa - p_maa,
               "median_ours": o_med, "median_paper": p_med, "median_diff": o_med - p_med}
        if per_seed is not None:
            v = np.asarray(per_seed[rate], dtype=float)
            row.update({"mAA_sd": float(v.std(ddof=1)) if v.size > 1 else 0.0, "mAA_min": float(v.min()),
                        "mAA_max": float(v.max()), "seeds_within": float(np.mean(np.abs(v - p_maa) <= band))})
        if oracle is not None:
            row["mAA_oracle"], row["median_oracle"] = oracle.get(rate, (np.nan, np.nan))
        rows.append(row)
    return pd.DataFrame(rows)


def calibration_markdown(table: pd.DataFrame, conf: dict[str, Any], iterations: int, seeds: list[int],
                         command: str, all_within: float | None = None, mkl_cbwr: str = "COMPATIBLE") -> str:
    """``mkl_cbwr``: the MKL_CBWR the run had (``numerics.portable_blas`` sets COMPATIBLE unless the user set one)."""
    from rlsac.data.lines import LineDataConf

    # the noise model only when it is not the default, as in the line files: the committed report keeps its bytes
    default_noise = LineDataConf.__dataclass_fields__["noise"].default
    settings = "\n".join(f"| {k} | {v} |" for k, v in conf.items()
                          if k not in ("outlier_rate", "seed") and not (k == "noise" and v == default_noise))
    mean_abs = table[["mAA_diff", "median_diff"]].abs().mean()
    worst = table.loc[table["mAA_diff"].abs().idxmax()]
    seed_text = f"{seeds[0]}" if len(seeds) == 1 else f"{seeds[0]}..{seeds[-1]} ({len(seeds)} seeds)"
    spread = ""
    if all_within is not None:
        spread = (f" One seed's row lies within ±0.03 of the paper at every rate for {all_within:.0%} of the "
                  f"seeds (`seeds_within`: the fraction per rate); `mAA_sd` is the seed-to-seed spread of one "
                  f"{conf['n_instances']}-instance set.")
    return f"""# Line generator calibration: our RANSAC vs the paper's RANSAC row (Table 1)

Generated by `{command}`; do not edit by hand.

For each outlier rate and each data seed {seed_text} the default (calibrated) `LineDataConf` set is
generated and our batched RANSAC (`rlsac.estimation.baselines.ransac`, {iterations} iterations, inlier threshold 0.1,
refinement by total least squares on the inliers, torch generator seeded with the data seed) is run on
it. The error is the angle to the ground-truth line in degrees; mAA is taken at 0.5 deg over 10
thresholds. `mAA_ours` and `median_ours` are means over the seeds; `diff` = ours - paper. `oracle` =
total least squares on the true inliers of the same instances: what any sampler followed by the same
refinement aims at, so `mAA_oracle - mAA_ours` is the headroom left to a better sampler such as RLSAC.
{_mkl_sentence(mkl_cbwr)}

## Generator settings (`LineDataConf`, outlier_rate and seed vary)

| field | value |
| --- | --- |
{settings}

## Result

{table.to_markdown(index=False, floatfmt=".3f")}

Mean |diff|: mAA {mean_abs['mAA_diff']:.3f}, median {mean_abs['median_diff']:.3f} deg; largest mAA gap
{worst['mAA_diff']:+.3f} at outlier rate {worst['outlier_rate']:g}.{spread}
"""


def _mkl_sentence(mkl_cbwr: str) -> str:
    if mkl_cbwr == "COMPATIBLE":
        return "MKL runs on its vendor-independent branch (`MKL_CBWR=COMPATIBLE`, `reports/platform.md`)."
    return (f"MKL ran with `MKL_CBWR={mkl_cbwr}` (set by the user), not on its vendor-independent branch: these "
            "numbers are this machine's (`reports/platform.md`).")


def calibrate_lines(options: dict[str, Any], track: bool = True,
                    params_path: str | Path | None = "params.yaml") -> dict:
    """``_calibrate_lines`` with MKL on its vendor-independent branch: the calibration gives the same bytes on
    Intel and AMD CPUs (the rest of the record is on its platform's branch, reports/platform.md)."""
    from rlsac import numerics

    with numerics.portable_blas():
        return _calibrate_lines(options, track, params_path, mkl_cbwr=os.environ["MKL_CBWR"])


def _calibrate_lines(options: dict[str, Any], track: bool = True,
                     params_path: str | Path | None = "params.yaml", mkl_cbwr: str = "COMPATIBLE") -> dict:
    """Run our RANSAC on the default line sets at outlier rates 0.1..0.7 and compare with the paper.

    options: n_instances (1000), seed (123), n_seeds (12: data seeds seed..seed+n_seeds-1, averaged),
    out (stem, "reports/calibration_lines"), iterations (150), device ("auto"), batch_size (256),
    rates (list, default 0.1..0.7), plus any LineDataConf field.
    Writes ``<out>.md`` and ``<out>.csv``; -> {"table": DataFrame, "md", "csv", "run_id"}.
    """
    from rlsac.data import lines
    from rlsac.estimation.baselines import oracle, ransac
    from rlsac.evaluation.evaluate import resolve_device, run_method, task_from

    o = {"n_instances": 1000, "seed": 123, "n_seeds": 12, "out": "reports/calibration_lines", "iterations": 150,
         "device": "auto", "batch_size": 256, "rates": sorted(PAPER_RANSAC_LINES)}
    o.update({k: v for k, v in options.items() if v is not None})
    device = resolve_device(o.pop("device"))
    out, rates = Path(o.pop("out")), o.pop("rates")
    iterations = config.check_value("iterations", o.pop("iterations"), int, "[1, inf)")
    batch_size = config.check_value("batch_size", o.pop("batch_size"), int, "[1, inf)")
    n_seeds = config.check_value("n_seeds", o.pop("n_seeds"), int, "[1, inf)")
    o["seed"] = config.check_value("seed", o["seed"], int, config.SEED_RANGE)
    seeds = [o["seed"] + k for k in range(n_seeds)]
    # validate all first: every rate's and every seed's settings, and both outputs
    confs = {float(r): line_conf({**o, "outlier_rate": float(r)}, params_path) for r in rates}
    line_conf({**o, "seed": seeds[-1]}, params_path)
    for suffix in (".md", ".csv"):
        check_writable(out.with_suffix(suffix))
    check_store(track, "lines")
    task = task_from("line")
    shown = config.to_dict(next(iter(confs.values())))
    command = (f"rlsac calibrate-lines --n-instances {shown['n_instances']} --seed {shown['seed']} "
               f"--n-seeds {n_seeds}")
    params = {"conf": {k: v for k, v in shown.items() if k != "outlier_rate"}, "iterations": iterations,
              "rates": list(confs), "n_seeds": n_seeds, "device": device, "batch_size": batch_size}
    with start_run("lines", f"calibrate-lines s{shown['seed']}x{n_seeds}", params=params,
                   tags={"command": "calibrate-lines"}, enabled=track) as run:
        ours, best, per_seed = {}, {}, {}
        from rlsac.progress import tqdm

        # one bar over the whole job (rates x data seeds; each run_method's own bar is a short inner one): the main
        # job of the README printed nothing for its 40 s (issue #47). Drawn on a terminal only (rlsac.progress)
        bar = tqdm(total=len(confs) * n_seeds, desc="calibrate-lines", unit="set")
        for rate, conf in confs.items():
            maa, med, omaa, omed = [], [], [], []
            for seed in seeds:
                bar.set_postfix_str(f"rate {rate:g}, data seed {seed}", refresh=False)
                c = dataclasses.replace(conf, seed=seed)
                data = lines.generate(c)
                errors, _ = run_method(task, lambda b, g: ransac(task, b, iterations, g), data, lines.to_batch,
                                       c.n_instances, seed, device, batch_size, desc=f"ransac o{rate:g} s{seed}")
                s = task.summarize(errors)
                maa.append(s["mAA"])
                med.append(s["median_deg"])
                errors, _ = run_method(task, lambda b, g: oracle(task, b), data, lines.to_batch,
                                       c.n_instances, seed, device, batch_size, desc=f"oracle o{rate:g} s{seed}")
                so = task.summarize(errors)
                omaa.append(so["mAA"])
                omed.append(so["median_deg"])
                bar.update()
            ours[rate], best[rate], per_seed[rate] = (np.mean(maa), np.mean(med)), (np.mean(omaa), np.mean(omed)), maa
            run.metrics({f"mAA_o{rate:g}": float(np.mean(maa)), f"median_deg_o{rate:g}": float(np.mean(med)),
                         f"mAA_sd_o{rate:g}": float(np.std(maa, ddof=1)) if len(maa) > 1 else 0.0,
                         f"oracle_mAA_o{rate:g}": float(np.mean(omaa))})
        bar.close()
        table = calibration_table(ours, oracle=best, per_seed=per_seed)
        by_seed = np.array([per_seed[r] for r in sorted(per_seed)]).T  # (n_seeds, rates)
        all_within = float(np.mean(np.all(np.abs(by_seed - table["mAA_paper"].to_numpy()) <= 0.03, axis=1)))
        md_path, csv_path = out.with_suffix(".md"), out.with_suffix(".csv")
        md = calibration_markdown(table, shown, iterations, seeds, command, all_within, mkl_cbwr)  # before either file
        with atomic_path(csv_path) as tmp:
            table.to_csv(tmp, index=False, float_format="%.4f")
        write_text(md_path, md)
        run.metrics({"mean_abs_mAA_diff": float(table["mAA_diff"].abs().mean()),
                     "max_abs_mAA_diff": float(table["mAA_diff"].abs().max()), "seeds_all_within": all_within,
                     "mean_abs_median_diff": float(table["median_diff"].abs().mean())})
        run.artifact(md_path)
        run.artifact(csv_path)
    return {"table": table, "md": str(md_path), "csv": str(csv_path), "run_id": run.run_id}


# ------------------------------------------------------------------------------------- data


def import_scenes(options: dict[str, Any], track: bool = True, write_matches: str | None = None):
    """``rlsac.data.scenes.import_scenes(ImportConf(**options))``."""
    from rlsac.data.scenes import ImportConf, import_scenes

    conf = _checked(ImportConf, options, "import-scenes", lambda c: [Path(c.out) / c.split / "import_summary.json"],
                    track)
    return import_scenes(conf, track=track, write_matches=write_matches)


def prepare_cvpr2020(options: dict[str, Any], track: bool = True):
    """``rlsac.data.tutorial.prepare(PrepareConf(**options))``."""
    from rlsac.data.tutorial import PrepareConf, prepare

    return prepare(_checked(PrepareConf, options, "prepare-cvpr2020", lambda c: [c.out], track), track=track)


def _checked(cls, options: dict[str, Any], what: str, outputs, track: bool):
    """``cls`` built from ``options`` (checked by config.build), after checking that ``outputs(conf)``
    and the tracking store can be written."""
    conf = config.build(cls, {k: v for k, v in options.items() if v is not None}, what)
    for path in outputs(conf):
        check_writable(path)
    check_store(track, "fundamental")
    return conf


# ---------------------------------------------------------------------------------------------- train


def train_options(task: str, flags: dict[str, Any], sets: tuple[str, ...] | list[str] = (),
                  params_path: str | Path | None = "params.yaml") -> dict[str, Any]:
    """params.yaml ``train.<task>`` <- CLI flags (None = not given) <- ``--set`` overrides."""
    options = section(read_params(params_path), "train", task)
    options["task"] = task
    options = deep_update(options, {k: v for k, v in flags.items() if v is not None})
    overrides = parse_sets(sets)
    options = deep_update(options, overrides)
    from rlsac.evaluation.train import OWN_SECTIONS

    method = str(options.get("method") or "rlsac")
    for key in overrides:  # params.yaml may hold both methods' sections; a --set of the other's would do nothing
        owner = next((m for m, secs in OWN_SECTIONS.items() if key in secs), method)
        if owner != method:
            raise RlsacError(f"--set {key}.*: an option of --method {owner}; --method {method} does not read it "
                             f"(its own: {', '.join(OWN_SECTIONS.get(method, ())) or 'none'})")
    return options


def train(options: dict[str, Any], track: bool = True):
    from rlsac.evaluation.train import train

    return train(options, track=track)
