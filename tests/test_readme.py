"""Every command the README, the docs/ pages (and experiments/README.md) show, and every example in the ``--help``
texts, is accepted as written: ``rlsac`` commands by the CLI parser, their ``--set KEY=VALUE`` overrides by the
configuration they override, ``dvc`` commands by DVC's parser with real stage names, ``mlflow`` commands by
MLflow's. Nothing heavy is run; the fresh-clone line is checked against what CI installs. Every 95% interval the
README, docs/ and reports/peers.md quote is one the generated tables hold, and every three-decimal number of the
README and docs/ is one a generated file holds; the README's results table is reports/paper.md's (issue #47).
"""

from __future__ import annotations

import re
import shlex
import sys
from pathlib import Path

import click
import pytest
from dvc import repo as dvc_repo
from dvc.cli import DvcParserError, parse_args

from rlsac.cli import cli
from rlsac.commands import train_options
from rlsac.config import build, parse_sets
from rlsac.data.lines import LineDataConf
from rlsac.data.scenes import ImportConf
from rlsac.data.tutorial import PrepareConf
from rlsac.evaluation.train import TrainConf
from rlsac.experiments import ablate as ablate_mod
from rlsac.reports import figures

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted((ROOT / "docs").glob("*.md"))  # the README's reference pages (issue #47)
DOCS = [ROOT / "README.md", ROOT / "experiments" / "README.md", *PAGES]
# the pages that must show commands (the test would otherwise pass on a page whose commands it failed to find)
COMMAND_PAGES = [ROOT / "experiments" / "README.md", ROOT / "docs" / "commands.md", ROOT / "docs" / "reproducing.md"]
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)
INLINE = re.compile(r"`((?:rlsac|dvc|mlflow|\.venv/bin/\w+) [^`]+)`")
PLACEHOLDER = re.compile(r"<[^>]+>|\.\.\.|\bCKPT\b|\bFILE\b|\bDIR\b|\bNAME\b|\bN\b|\bCOMMAND\b")
VENV_TOOLS = {"rlsac", "dvc", "mlflow", "python", "pip", "pytest", "ruff"}


# ----------------------------------------------------------------------------------------------- reading


def _commands(line: str) -> list[list[str]]:
    """One shell line -> its commands (split at &&, ;), comments dropped, ``.venv/bin/`` prefixes removed."""
    argv = shlex.split(line, comments=True)
    out, cur = [], []
    for tok in argv:
        if tok in ("&&", ";", "||"):
            out.append(cur)
            cur = []
        else:
            cur.append(tok)
    out.append(cur)
    cmds = []
    for c in out:
        if c and c[0].startswith(".venv/bin/") and c[0].split("/")[-1] in VENV_TOOLS:
            c = [c[0].split("/")[-1], *c[1:]]
        if c:
            cmds.append(c)
    return cmds


def block_commands(text: str) -> list[tuple[str, list[str]]]:
    """(line, argv) of every command in the fenced bash blocks of ``text``."""
    found = []
    for lang, body in FENCE.findall(text):
        if lang not in ("bash", "sh"):
            continue
        for line in body.replace("\\\n", " ").splitlines():
            if line.strip() and not line.lstrip().startswith("#"):
                found += [(line, argv) for argv in _commands(line)]
    return found


def inline_commands(text: str) -> list[tuple[str, list[str], bool]]:
    """(text, argv, complete) of commands in backticks outside code blocks; ``complete`` = a first table cell
    (a full command line) rather than a mention in prose (which may leave out required options)."""
    prose = FENCE.sub("", text)
    found = []
    for line in prose.splitlines():
        first_cell = line.startswith("| `")
        for i, m in enumerate(INLINE.finditer(line)):
            s = m.group(1).replace("\\|", "|")
            if PLACEHOLDER.search(s) or "|" in s:
                continue
            for argv in _commands(s):
                found.append((s, argv, first_cell and i == 0))
    return found


def help_texts() -> list[tuple[str, str]]:
    """(command, help text) of the group, every command and every option."""
    out = [("", cli.help or "")]
    for name, cmd in cli.commands.items():
        out.append((name, cmd.help or ""))
        for p in cmd.params:
            if isinstance(p, click.Option):
                out.append((name, p.help or ""))
    return out


# ---------------------------------------------------------------------------------------------- checking


SET_CONF = {"import-scenes": ImportConf, "prepare-cvpr2020": PrepareConf}


def check_sets(command: str, sets: list[str], task: str = "line") -> None:
    """Apply ``--set`` overrides the way the command does; raises on an unknown key or a bad value."""
    overrides = parse_sets(sets)
    if command == "train":
        build(TrainConf, train_options(task, {}, sets, ROOT / "params.yaml"), "train")
    elif command in SET_CONF:
        build(SET_CONF[command], overrides, SET_CONF[command].__name__)
    elif command == "plot":
        figures._options(overrides)
    elif command == "ablate":
        ablate_mod.check_options({"what": "all", **overrides})
    elif overrides:
        raise AssertionError(f"rlsac {command} takes no --set")


def check_rlsac(argv: list[str], complete: bool = True) -> None:
    if argv[1:] and argv[1] in ("--help", "-h", "--version"):
        return
    assert len(argv) >= 2 and argv[1] in cli.commands, f"unknown rlsac command: {argv}"
    cmd = cli.commands[argv[1]]
    if complete:
        ctx = cmd.make_context(argv[1], argv[2:])  # unknown option, bad value or missing required option
        sets = list(ctx.params.get("sets") or [])
        check_sets(argv[1], sets, ctx.params.get("task") or "line")
        if ctx.params.get("method") == "rlsac":
            assert ctx.params.get("checkpoint"), f"{argv}: --method rlsac needs --checkpoint"
    else:
        known = {o for p in cmd.params for o in (*p.opts, *p.secondary_opts)}
        for tok in argv[2:]:
            if tok.startswith("-"):
                assert tok.split("=")[0] in known, f"rlsac {argv[1]}: unknown option {tok}"


_STAGES: dict[str, set[str]] = {}


def _stage_names(where: Path) -> set[str]:
    if str(where) not in _STAGES:
        with dvc_repo.Repo(str(where)) as repo:
            names = {s.name for s in repo.index.stages}
        _STAGES[str(where)] = names | {n.split("@")[0] for n in names}
    return _STAGES[str(where)]


def check_dvc(argv: list[str]) -> None:
    try:
        args = parse_args(argv[1:])
    except DvcParserError as e:
        raise AssertionError(f"dvc rejects {shlex.join(argv)}") from e
    where = ROOT / (args.cd or ".")
    assert (where / "dvc.yaml").exists(), f"{shlex.join(argv)}: no dvc.yaml in {where}"
    if args.func.__name__ == "CmdRepro" or argv[1:].count("repro") or "repro" in argv:
        for t in getattr(args, "targets", None) or []:
            assert t in _stage_names(where), f"{shlex.join(argv)}: no stage {t!r} (`dvc stage list`)"


def check_mlflow(argv: list[str]) -> None:
    from mlflow.cli import cli as mlflow_cli

    cmd = mlflow_cli.get_command(click.Context(mlflow_cli), argv[1])  # `ui` is an alias of `server`
    assert cmd is not None, f"mlflow has no command {argv[1]}"
    cmd.make_context(argv[1], argv[2:])


EXPORTS = {"MLFLOW_TRACKING_URI", "OMP_NUM_THREADS", "RAY_AUTH_TOKEN", "RAY_AUTH_MODE", "AWS_ACCESS_KEY_ID",
           "AWS_SECRET_ACCESS_KEY", "AWS_ENDPOINT_URL"}  # the last three: rlsac pipeline --remote's bucket


def check_ray(argv: list[str]) -> None:
    from ray.scripts.scripts import cli as ray_cli

    cmd = ray_cli.get_command(click.Context(ray_cli), argv[1])
    assert cmd is not None, f"ray has no command {argv[1]}"
    cmd.make_context(argv[1], argv[2:])


def check_other(argv: list[str], line: str) -> None:
    prog = argv[0]
    if prog == "python3":
        assert argv[1:3] == ["-m", "venv"], line
    elif prog == ".":
        assert argv[1] == ".venv/bin/activate", line
    elif prog == "pip":
        assert argv[1] == "install" and "-e" in argv and ".[dev]" in argv, line
        pins = [a for a in argv[2:] if "==" in a]
        assert pins and all(f'"{pin}"' in (ROOT / "pyproject.toml").read_text() for pin in pins), \
            f"{line}: its pins are not pyproject.toml's"
        if "-c" in argv:  # the constraints file pins what changes output bytes; it agrees with pyproject's pins
            constraints = (ROOT / argv[argv.index("-c") + 1]).read_text().split()
            assert all(pin in constraints for pin in pins), f"{line}: constraints file disagrees with {pins}"
    elif prog == "python":
        assert argv[1:3] == ["-m", "pytest"] or (argv[1].startswith("benchmarks/") and (ROOT / argv[1]).is_file()), line
    elif prog == "ray":
        check_ray(argv)
    elif prog == "export":
        assert len(argv) == 2 and argv[1].split("=")[0] in EXPORTS, line
    elif prog == "bash":
        assert (ROOT / argv[1]).is_file(), line
    elif prog == "mlflow":
        check_mlflow(argv)
    elif prog == "cmp":  # a by-hand result against the committed one (issue #47): that one must exist
        assert len(argv) == 3 and (ROOT / argv[2]).is_file(), line
    else:
        raise AssertionError(f"a README command this test does not know how to check: {line}")


def check(argv: list[str], line: str, complete: bool = True) -> None:
    if argv[0] == "rlsac":
        check_rlsac(argv, complete)
    elif argv[0] == "dvc":
        check_dvc(argv)
    else:
        check_other(argv, line)


def ci_runs_readme_blocks() -> list[str]:
    """The README blocks .ci/run evaluates, as its readme_block function extracts them (awk, run here)."""
    import subprocess

    ci = (ROOT / ".ci" / "run").read_text()
    func = re.search(r"^readme_block\(\) \{\n.*?^\}", ci, re.S | re.M).group(0)
    n = [int(k) for k in re.findall(r'^eval "\$\(readme_block (\d)\)"', ci, re.M)]
    return [subprocess.run(["bash", "-c", f"{func}\nreadme_block {k}"], cwd=ROOT, check=True, capture_output=True,
                           text=True).stdout.strip() for k in n]


# ------------------------------------------------------------------------------------------------- tests


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_code_block_command_is_accepted(doc):
    found = block_commands(doc.read_text())
    assert found or doc.name != "README.md" and doc not in COMMAND_PAGES  # a page without commands: nothing to check
    for line, argv in found:
        check(argv, line)


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_inline_command_is_accepted(doc):
    found = inline_commands(doc.read_text())
    assert found or doc not in COMMAND_PAGES
    for text, argv, complete in found:
        check(argv, text, complete)


def test_readme_starts_with_the_two_fresh_clone_commands():
    """The first two code blocks: install + the main job (in the venv it activates: RLSAC against its controls on
    one fold's shipped pairs, rlsac quick), then the tests; the install is the one CI makes."""
    text = (ROOT / "README.md").read_text()
    blocks = [body.strip() for lang, body in FENCE.findall(text) if lang == "bash"]
    assert text[:text.index("```bash")].count("\n") < 30, "the two commands come first, after the verdict"
    first, second = blocks[0], blocks[1]
    assert "\n" not in first and "\n" not in second
    cmds = _commands(first)
    assert [c[0] for c in cmds] == ["python3", ".", "pip", "rlsac"]
    assert cmds[1] == [".", ".venv/bin/activate"]  # later bare rlsac/dvc/mlflow commands find the venv
    assert cmds[3] == ["rlsac", "quick"]
    assert _commands(second) == [["python", "-m", "pytest", "-q", "-n", "auto"]]
    assert second.startswith(".venv/bin/python")
    for argv in cmds:
        check(argv, first)
    assert ci_runs_readme_blocks() == [first, second], ".ci/run runs the README's two commands as written"


def test_every_rlsac_command_is_documented():
    text = (ROOT / "docs" / "commands.md").read_text()
    for name in cli.commands:
        assert f"`rlsac {name}" in text, f"rlsac {name} missing from docs/commands.md's command table"
    assert "--method oracle" in text


def test_help_examples_are_accepted():
    seen = 0
    for command, text in help_texts():
        for m in re.finditer(r"--set\s+([\w.]+=\S+?)(?=[.,;)]?(?:\s|$))", text):
            check_sets(command, [m.group(1)])
            seen += 1
        for m in re.finditer(r"`(rlsac [^`]+)`", text):
            check_rlsac(shlex.split(m.group(1)), complete=False)
    assert seen >= 1


DEFAULT = re.compile(r"\[default: ([^\]]+)\]")
HELP_CONF = {"synth-lines": LineDataConf, "import-scenes": ImportConf, "prepare-cvpr2020": PrepareConf}


@pytest.mark.parametrize("command", list(HELP_CONF))
def test_help_defaults_are_the_real_ones(command):
    """A literal ``[default: X]`` in an option's help is the configuration's default for that field."""
    conf = HELP_CONF[command]()
    checked = 0
    for p in cli.commands[command].params:
        m = DEFAULT.search(getattr(p, "help", None) or "")
        if not m or not hasattr(conf, p.name):
            continue
        shown, real = m.group(1).strip(), getattr(conf, p.name)
        if isinstance(real, bool):
            if shown in ("on", "off"):
                assert shown == ("on" if real else "off"), f"{command} --{p.name}: help {shown}, real {real}"
                checked += 1
        elif isinstance(real, (int, float)):
            try:
                value = float(shown)
            except ValueError:
                continue
            assert value == real, f"{command} {p.opts[0]}: help says {shown}, the default is {real}"
            checked += 1
        elif isinstance(real, str) and "/" in shown:
            assert shown == real, f"{command} {p.opts[0]}: help says {shown}, the default is {real}"
            checked += 1
    assert checked >= 2


def test_checker_rejects_what_the_issue_found():
    """The examples the issue reported as rejected are rejected by these checks (the checks bite)."""
    with pytest.raises(Exception, match="lr"):
        check_sets("train", ["sac.lr=1e-4"])
    with pytest.raises(Exception, match="optim"):
        check_sets("train", ["optim.lr=1e-4"])
    with pytest.raises(click.UsageError):
        check_rlsac(["rlsac", "evaluate", "--task", "line", "--method", "nope", "--data", "x.h5"])
    with pytest.raises(AssertionError):
        check_dvc(["dvc", "repro", "-s", "no_such_stage"])
    with pytest.raises(AssertionError):
        check_dvc(["dvc", "metrics", "show", "--no-such-option"])
    with pytest.raises(AssertionError):
        check_other(["pip", "install", "torch==2.0.0", "-e", ".[dev]"], "pip install torch==2.0.0 -e .[dev]")


if __name__ == "__main__":  # print what is checked
    for doc in DOCS:
        for _line, argv in block_commands(doc.read_text()):
            print(doc.name, shlex.join(argv), file=sys.stdout)


# ------------------------------------------------------------------------------------ quoted intervals
INTERVAL = re.compile(r"([+\-−]?\d\.\d{3}) \[([+\-−]?\d\.\d{3}), ([+\-−]?\d\.\d{3})\]")
# the pages that quote the pipeline's results by hand, and the generated files they quote from (`rlsac table`)
QUOTING = [ROOT / "README.md", ROOT / "reports" / "peers.md", ROOT / "reports" / "folds.md", *PAGES]


def quoted_intervals(text: str) -> set[tuple[float, float, float]]:
    """Every `d [lo, hi]` of a text (3 decimals, either minus sign, across line breaks), as rounded numbers."""
    def number(s: str) -> float:
        return round(float(s.replace("−", "-")), 3) + 0.0  # + 0.0: -0.000 and +0.000 are one number

    return {tuple(number(x) for x in m) for m in INTERVAL.findall(" ".join(text.split()))}


def generated_intervals(reports: Path) -> set[tuple[float, float, float]]:
    names = ("claims", "selection", "paper", "scale", "positive_control", "tuning_budget", "learner")
    files = sorted(reports.glob("table*.md")) + [reports / f"{n}.md" for n in names]
    return set().union(*(quoted_intervals(f.read_text()) for f in files if f.is_file()))


@pytest.mark.parametrize("doc", QUOTING, ids=lambda p: p.name)
def test_every_quoted_interval_is_one_of_the_generated_tables(doc):
    """A number the README or a hand-written report quotes with its 95% interval is one that `rlsac table` wrote
    (reports/table*.md, claims.md, selection.md, paper.md, scale.md, positive_control.md, learner.md): no interval
    computed by hand, none left from an earlier record."""
    stale = sorted(quoted_intervals(doc.read_text()) - generated_intervals(ROOT / "reports"))
    assert not stale, f"{doc.name}: {len(stale)} interval(s) in no generated table, e.g. {stale[:3]}"


def test_interval_check_finds_a_stale_quote(tmp_path):
    (tmp_path / "table2_folds.md").write_text("| −0.050 [−0.075, −0.027] | +0.000 [-0.021,\n +0.021] |")
    assert generated_intervals(tmp_path) == {(-0.05, -0.075, -0.027), (0.0, -0.021, 0.021)}
    quoted = quoted_intervals("loses in t (−0.050 [−0.073,\n  −0.025]); R −0.000 [−0.021, +0.021]")
    assert quoted - generated_intervals(tmp_path) == {(-0.05, -0.073, -0.025)}


# ------------------------------------------------------------------------------------ quoted point values (issue #47)
# (not part of a dotted address or version: 192.168.*, 1.2.345.6)
POINT = re.compile(r"(?<![\w.])([+\-−]?)(\d+\.\d{3})(?!\d)(?!\.[\d*])")
# files `rlsac table`, `rlsac calibrate-lines` and benchmarks/line_landscape.py write (the hand-written pages are not)
GENERATED = ("table*.md", "claims.md", "selection.md", "paper.md", "scale.md", "positive_control.md", "learner.md",
             "tuning_budget.md", "calibration_*.md", "*.csv", "metrics.json")


def point_values(text: str) -> set[float]:
    """Every number with three decimals (the tables' precision) of a text, signed (no sign: positive)."""
    return {round(float(v) * (-1 if sign in "-−" and sign else 1), 3) + 0.0 for sign, v in POINT.findall(text)}


def generated_values(reports: Path) -> set[float]:
    """Every three-decimal number the generated files print as such (a longer float is not rounded to match)."""
    return set().union(*(point_values(f.read_text()) for pattern in GENERATED for f in sorted(reports.glob(pattern))))


@pytest.mark.parametrize("doc", [ROOT / "README.md", *PAGES], ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_quoted_number_is_a_generated_one(doc):
    """A three-decimal number the README or a docs/ page quotes (an mAA, a difference, an interval end) is one a
    generated report holds: no number typed from an earlier record."""
    stale = sorted(point_values(doc.read_text()) - generated_values(ROOT / "reports"))
    assert not stale, f"{doc.name}: {len(stale)} number(s) in no generated file, e.g. {stale[:5]}"


def test_point_values_are_numbers_not_addresses():
    assert point_values("mAA 0.735, −0.013 [−0.034, +0.009]; hosts 192.168.*, 10.1.234.5") == \
        {0.735, -0.013, -0.034, 0.009}


def test_point_value_check_finds_a_stale_number(tmp_path):
    (tmp_path / "claims.md").write_text("| 0.735 ± 0.019 | −0.013 [−0.034, +0.009] |")
    (tmp_path / "x.csv").write_text("a,b\n0.73649,-0.500\n")
    assert generated_values(tmp_path) == {0.735, 0.019, -0.013, -0.034, 0.009, -0.5}
    assert point_values("RLSAC 0.736 (−0.013), 0.735, 0.500") - generated_values(tmp_path) == {0.736, 0.5}


def test_the_readme_opens_with_paper_mds_verdict():
    """The README's first 25 lines hold paper.md's "In short" word for word, before the install command (issue #62):
    its sentences and every number in them are the generated page's, so the prose cannot drift from the table."""
    text = (ROOT / "README.md").read_text()
    short = (ROOT / "reports" / "paper.md").read_text().split("## In short\n\n", 1)[1].split("\n\n", 1)[0]
    first = "\n".join(text.splitlines()[:25])
    assert " ".join(short.split()) in " ".join(first.split()), "README's verdict is not paper.md's In short"
    assert first.index("mAA R") < text.index("```bash") and 3 <= short.count(". ") + 1 <= 5
    for term in ("mAA R / t:", "regime *hard*:", "regime *easy*", "selection term, what"):  # defined where first used
        assert term in first


def test_the_readme_is_short_and_its_results_table_is_paper_md():
    """The README's first screen is the answer (issue #47): under 2,500 words, and its results table is the "At a
    glance" table of the generated reports/paper.md, row for row, with at most 15 rows."""
    text = (ROOT / "README.md").read_text()
    assert len(text.split()) < 2500
    paper_md = (ROOT / "reports" / "paper.md").read_text()
    glance = paper_md.split("## At a glance", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in glance.splitlines() if line.startswith("|")]
    assert 3 <= len(rows) <= 17 and all(line in text for line in rows), "README's table is not paper.md's"
    assert text.index(rows[0]) < text.index("## Documentation")
    counts = re.search(r"^\d+ rows: (.*)\.$", paper_md, re.M)
    assert f"In reports/paper.md: {counts.group(1)} (of {counts.group(0).split()[0]} rows)" in " ".join(text.split())
    for link in ("reports/paper.md", "reports/folds.md", "reports/claims.md"):
        assert f"]({link})" in text
    for page in PAGES:
        assert f"](docs/{page.name})" in text, f"docs/{page.name} is not linked from the README"


def test_docs_quote_the_claims_count_line_of_claims_md():
    """docs/results.md quotes reports/claims.md's count line as generated (it quoted 36 / 24 when claims.md had 41)."""
    counts = re.search(r"^(\d+ claims: .*)$", (ROOT / "reports" / "claims.md").read_text(), re.M).group(1)
    assert counts in " ".join((ROOT / "docs" / "results.md").read_text().split())
