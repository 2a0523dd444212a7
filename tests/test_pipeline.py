"""dvc.yaml and the two profiles stay consistent: every command is an ``rlsac`` call that the CLI accepts,
every templated value and every listed param exists in both params files, and the ablation plan in
params.yaml is coherent. Nothing is run."""

from __future__ import annotations

import os
import re
import shlex
import sys
from pathlib import Path

import pytest
import yaml
from dvc import repo as dvc_repo

from rlsac.cli import cli
from rlsac.config import build, check_params
from rlsac.evaluation.train import TrainConf
from rlsac.experiments import ablate

ROOT = Path(__file__).resolve().parents[1]
PROFILES = {"paper": ROOT, "quick": ROOT / "experiments" / "quick"}
REF = re.compile(r"\$\{([^}]+)\}")


def _load(path: Path) -> dict:
    return yaml.safe_load(path.read_text())


def _lookup(params: dict, dotted: str):
    d = params
    for part in dotted.split("."):
        if not isinstance(d, dict) or part not in d:
            raise KeyError(dotted)
        d = d[part]
    return d


@pytest.fixture(scope="module")
def pipeline() -> dict:
    return _load(ROOT / "dvc.yaml")


def _stage_bodies(pipeline: dict):
    for name, st in pipeline["stages"].items():
        yield name, st.get("do", st)


def test_quick_dvc_yaml_is_the_same_pipeline():
    link = PROFILES["quick"] / "dvc.yaml"
    assert link.is_symlink() and link.resolve() == (ROOT / "dvc.yaml").resolve()


def test_quick_profile_ignores_what_the_root_ignores():
    """The quick profile's lock hashes the outputs the paper profile's does: without the root's .dvcignore it hashed
    each evaluation's timing.json, so no two runs' locks were alike (issue #50)."""
    import subprocess

    link = PROFILES["quick"] / ".dvcignore"
    assert link.is_symlink() and link.resolve() == (ROOT / ".dvcignore").resolve()
    timing = "reports/eval/lines/ransac/o0.5/timing.json"
    r = subprocess.run([sys.executable, "-m", "dvc", "check-ignore", "-q", timing], cwd=PROFILES["quick"])
    assert r.returncode == 0


def test_quick_profile_is_its_own_dvc_project():
    """The quick profile is a DVC project of its own without git (`dvc --cd experiments/quick repro`): the
    repository's DVC commands (params diff, metrics show, plots show at HEAD) never read its symlinked
    dvc.yaml or its missing outputs, and its lock file, rewritten by every run, stays out of git."""
    import subprocess

    quick = PROFILES["quick"]
    with dvc_repo.Repo(str(ROOT)) as repo:
        assert repo.root_dir == str(ROOT)
        assert not [s for s in repo.index.stages if Path(os.path.abspath(s.path)).parent != ROOT]
    with dvc_repo.Repo(str(quick)) as repo:
        assert repo.root_dir == str(quick) and type(repo.scm).__name__ == "NoSCM"  # git-ignored dvc.lock allowed
        assert {s.name.split("@")[0] for s in repo.index.stages} >= {"lines_data", "tables", "figures"}
    rel = quick.relative_to(ROOT)
    tracked = subprocess.run(["git", "ls-files", str(rel)], cwd=ROOT, check=True, capture_output=True,
                             text=True).stdout.split()
    assert str(rel / ".dvc" / "config") in tracked and str(rel / "dvc.lock") not in tracked
    for written in ("dvc.lock", ".dvc/tmp/x", ".dvc/cache/x", "data/x", "checkpoints/x", "reports/x", "mlflow.db"):
        assert subprocess.run(["git", "check-ignore", "-q", str(rel / written)], cwd=ROOT).returncode == 0, written
    assert subprocess.run(["git", "check-ignore", "-q", "dvc_plots/index.html"], cwd=ROOT).returncode == 0


def test_profiles_have_the_same_keys():
    paper, quick = (_load(p / "params.yaml") for p in PROFILES.values())
    assert sorted(paper) == sorted(quick)
    for section in ("lines", "fundamental", "ablation", "evaluate", "essential"):
        assert sorted(paper[section]) == sorted(quick[section]), section
        for k, v in paper[section].items():
            if isinstance(v, dict) and k not in ("models", "variants"):
                assert sorted(v) == sorted(quick[section][k]), f"{section}.{k}"
    assert sorted(paper["train"]) == sorted(quick["train"])
    for task, opts in paper["train"].items():
        assert sorted(opts) == sorted(quick["train"][task]), f"train.{task}"
        for k, v in opts.items():  # a paper option group (policy, sac, ...): quick may add CI-size knobs only
            if isinstance(v, dict):
                assert set(v) <= set(quick["train"][task][k]), f"train.{task}.{k}"
    for p in (paper, quick):
        for task, opts in p["train"].items():
            build(TrainConf, {**(opts or {}), "task": task}, f"train.{task}")  # unknown keys raise
        check_params(p)  # every section as every rlsac command checks it when it reads the file


def test_commands_are_rlsac_calls(pipeline):
    for name, body in _stage_bodies(pipeline):
        for part in re.split(r"\s*&&\s*", " ".join(body["cmd"].split())):
            assert part.startswith("rlsac "), f"{name}: {part}"


@pytest.mark.parametrize("profile", list(PROFILES))
def test_templated_values_and_params_exist(pipeline, profile):
    params = _load(PROFILES[profile] / "params.yaml")
    for ref in set(REF.findall(yaml.safe_dump(pipeline))):  # values only, not the comments
        if ref in ("item", "key") or ref.startswith("item."):
            continue
        _lookup(params, ref)
    for name, st in pipeline["stages"].items():
        body = st.get("do", st)
        for item in _items(params, st):
            for p in body.get("params", []):
                assert isinstance(p, str), f"{name}: params must name keys of params.yaml"
                # ${item.x} from the instance, any other ${key} from params (folds.pool.${folds.model_regime})
                _lookup(params, REF.sub(lambda m, item=item: str(item[m.group(1)] if m.group(1) in item
                                                                 else _lookup(params, m.group(1))), p))


def _values(params: dict, ref) -> list:
    if isinstance(ref, str) and REF.fullmatch(ref.strip()):
        ref = _lookup(params, REF.fullmatch(ref.strip()).group(1))
    return list(ref)


def _items(params: dict, stage: dict) -> list[dict]:
    """The substitutions of each instance of a foreach or matrix stage (``${key}``, ``${item}``, ``${item.x}``)."""
    if "matrix" in stage:
        axes = {k: _values(params, v) for k, v in stage["matrix"].items()}
        combos = [{}]
        for k, vals in axes.items():
            combos = [{**c, f"item.{k}": v} for c in combos for v in vals]
        return combos
    if "foreach" in stage:
        over = _lookup(params, REF.fullmatch(stage["foreach"].strip()).group(1))
        if isinstance(over, dict):
            return [{"key": k, "item": v} for k, v in over.items()]
        return [{"item": v} for v in over]
    return [{}]


@pytest.mark.parametrize("profile", list(PROFILES))
def test_dvc_renders_and_cli_accepts_every_command(profile):
    """DVC's own templating renders each profile; click parses every rendered command line."""
    with dvc_repo.Repo(str(PROFILES[profile])) as repo:
        stages = [s for s in repo.index.stages
                  if Path(os.path.abspath(s.path)).parent == PROFILES[profile] and s.cmd]  # no symlink resolving
    names = {s.name.split("@")[0] for s in stages}
    assert {"lines_data", "train_lines", "import_scenes", "fold_data", "fold_train", "fold_eval", "fold_eval_model",
            "essential_train", "essential_eval", "tables", "figures"} <= names
    assert any(s.metrics for s in stages), "the tables stage declares reports/metrics.json"
    for s in stages:
        for part in re.split(r"\s*&&\s*", s.cmd):
            argv = shlex.split(part)
            assert argv[0] == "rlsac", s.name
            cmd = cli.commands.get(argv[1])
            assert cmd is not None, f"{s.name}: unknown command {argv[1]}"
            cmd.make_context(argv[1], argv[2:])  # raises on an unknown option or a bad value


@pytest.mark.parametrize("profile", list(PROFILES))
def test_ablation_plan_is_coherent(profile):
    params = _load(PROFILES[profile] / "params.yaml")
    p = ablate.protocol(params)
    for name, v in p["variants"].items():
        assert Path(v["checkpoint"]) == ablate.model_checkpoint(v["model"]), name
        if v["model"] != ablate.FULL:
            assert v["suffix"] == p["models"][v["model"]]["suffix"], name
    assert {f"_n{n}" for n in p["n_points"]} == {m["suffix"] for m in p["models"].values() if m["suffix"]}
    assert set(ablate.DEFAULTS["variants"]) == set(p["variants"])
    for what in ablate.STUDIES + ("all",):
        o = ablate.check_options({"what": what})
        plan = ablate.plan(o, params)
        assert "full" in plan["variants"]
        for e in plan["variants"].values():
            assert e["iterations"] == p["iterations"] and e["sampling"] in ("max", "prob")
    gen = ablate.plan(ablate.check_options({"what": "generalisation"}), params)
    rates = params["lines"]["rates"]
    assert len(gen["variants"]) == len(rates)
    src = f"{float(p['generalisation']['train_rate']):g}"
    assert all(e["checkpoint"] == str(Path("checkpoints") / f"line_o{src}.pt") for e in gen["variants"].values())


def _resolved_stages(root: Path) -> list:
    with dvc_repo.Repo(str(root)) as repo:
        return [(s.addressing, [str(d.def_path) for d in s.deps if not hasattr(d, "params")],
                 {p for d in s.deps if hasattr(d, "params") for p in (d.params or [])},
                 [(str(o.def_path), o.use_cache) for o in s.outs])
                for s in repo.index.stages if Path(os.path.abspath(s.path)).parent == root]


def test_each_stage_depends_on_its_own_recipe_and_no_ignored_file():
    """Issue #25: a fold model depends on its own recipe (folds.train.<model>), not on the mapping of every model,
    so adding a model does not re-train the others; an evaluation depends on the one checkpoint it reads, and a
    training stage never on the test file; no dependency is a git-ignored file that no stage makes (the fold
    checkpoint folder held git-ignored *.state.pt files, so a clone could never be up to date)."""
    import subprocess

    stages = _resolved_stages(ROOT)
    outs = {o for _, _, _, os_ in stages for o, _ in os_}
    f = _load(ROOT / "params.yaml")["folds"]
    # the file models train on the fold's files (fold_train); the pool models (RLSAC at scale) on its pool too
    trains = [s for s in stages if s[0].startswith("fold_train@")]
    pools = [s for s in stages if s[0].startswith("fold_train_pool@")]
    # (the paper profile's pool model waits outside the lists until its runs are recorded: the quick profile has one)
    assert len(trains) == 4 * len(f["file_models"]) and len(pools) == 4 * len(f["pool_models"])
    assert sorted(f["file_models"] + f["pool_models"]) == sorted(f["models"])
    seeded = [s for s in stages if s[0].startswith(("fold_train_seed@", "fold_train_pool_seed@"))]
    assert len(seeded) == 4 * len(f["seed_models"]) * len(f["seeds"])
    for name, deps, params, _ in trains + pools + seeded:
        fold, model = name.split("@")[1].split("-", 1)
        recipe = re.sub(r"-\d+$", "", model) if name.startswith(("fold_train_seed@", "fold_train_pool_seed@")) \
            else model
        assert f"folds.train.{recipe}" in params and "folds.train" not in params, name
        assert not any(d.endswith("test.h5") for d in deps), name
        assert (f"data/folds/pool/{fold}.h5" in deps) == (recipe in f["pool_models"]), name
    for name, deps, _params, _ in stages:
        for d in deps:
            made = d in outs or any(d.startswith(o.rstrip("/") + "/") for o in outs)
            ignored = subprocess.run(["git", "check-ignore", "-q", d], cwd=ROOT).returncode == 0
            assert made or not ignored, f"{name}: {d} is git-ignored and no stage makes it"
            if d.startswith("checkpoints/"):
                # a folder only where the stage reads every file in it: the figures, and the scale study's runs (each
                # run's folder holds its step snapshots; the report reads every run)
                assert d.endswith(".pt") or name == "figures" or d.startswith("checkpoints/scale/") or \
                    d == "checkpoints/scale", f"{name}: depends on the folder {d}"
        if name.startswith(("fold_eval_model@", "fold_eval_lo@")):
            _regime, fold, model = name.split("@")[1].split("-", 2)
            want = [f"checkpoints/folds/hard/{fold}/{model}.pt"]
            assert [d for d in deps if d.startswith("checkpoints/")] == want, name


def test_timings_and_training_states_are_ignored_by_git_and_dvc():
    """Outputs DVC hashes and git commits hold no per-run file: timing.json sidecars and training states."""
    import subprocess

    for path in ("reports/eval/folds/hard/castle/magsac/i100/timing.json",
                 "checkpoints/folds/hard/castle/rlsac.pt.state.pt"):
        assert subprocess.run(["git", "check-ignore", "-q", path], cwd=ROOT).returncode == 0, path
    dvcignore = (ROOT / ".dvcignore").read_text().split()
    assert "timing.json" in dvcignore and "*.state.pt" in dvcignore
