"""dvc.yaml and the two profiles stay consistent: every command is an ``rlsac`` call that the CLI accepts,
every templated value and every listed param exists in both params files, and the ablation plan in
params.yaml is coherent. Nothing is run."""

from __future__ import annotations

import os
import re
import shlex
from pathlib import Path

import pytest
import yaml
from dvc import repo as dvc_repo

from rlsac import ablate
from rlsac.cli import cli
from rlsac.config import build
from rlsac.train import TrainConf

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
        keys = [None]
        if "foreach" in st:
            over = _lookup(params, REF.fullmatch(st["foreach"].strip()).group(1))
            keys = list(over) if isinstance(over, dict) else [None]
        for key in keys:
            for p in body.get("params", []):
                assert isinstance(p, str), f"{name}: params must name keys of params.yaml"
                _lookup(params, p.replace("${key}", str(key)))


@pytest.mark.parametrize("profile", list(PROFILES))
def test_dvc_renders_and_cli_accepts_every_command(profile):
    """DVC's own templating renders each profile; click parses every rendered command line."""
    with dvc_repo.Repo(str(PROFILES[profile])) as repo:
        stages = [s for s in repo.index.stages
                  if Path(os.path.abspath(s.path)).parent == PROFILES[profile] and s.cmd]  # no symlink resolving
    names = {s.name.split("@")[0] for s in stages}
    assert {"lines_data", "train_lines", "eval_fundamental", "ablation_train", "ablation_eval", "tables",
            "figures"} <= names
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


def test_repro_script_lanes_cover_every_stage_once():
    """experiments/repro_paper.sh runs each paper stage in exactly one lane, and only real stages."""
    import subprocess

    out = subprocess.run(["bash", str(ROOT / "experiments" / "repro_paper.sh"), "--list"], check=True,
                         capture_output=True, text=True).stdout
    listed = [line.split() for line in out.splitlines()]
    with dvc_repo.Repo(str(ROOT)) as repo:
        names = [s.name for s in repo.index.stages
                 if Path(os.path.abspath(s.path)).parent == PROFILES["paper"] and s.cmd]
    lane_of: dict[str, list[str]] = {name: [] for name in names}
    for lane, target in listed:
        hits = [n for n in names if n == target or n.split("@")[0] == target]
        assert hits, f"{lane}: {target} is not a stage"
        for n in hits:
            lane_of[n].append(lane)
    assert {n: lanes for n, lanes in lane_of.items() if len(lanes) != 1} == {}
