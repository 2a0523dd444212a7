"""The ``rlsac`` command line. Each command parses options and calls one library function.

A user error (``RlsacError``, or one of click's usage errors) is printed as ``error: <message>`` on one line of
stderr with exit code 2 and no traceback.
"""

from __future__ import annotations

import os
import sys

import click

from rlsac import numerics
from rlsac.errors import RlsacError
from rlsac.evaluation.methods import METHODS
from rlsac.experiments.scale import STAGES as SCALE_STAGES  # light: the study's code loads when a stage runs


class _UserError(click.ClickException):
    exit_code = 2

    def __init__(self, message: str, exit_code: int = 2):
        super().__init__(message)
        self.exit_code = exit_code

    def show(self, file=None) -> None:
        click.echo(f"error: {self.format_message()}", err=True)


# what torch's CPU and CUDA allocators say when an allocation fails (a RuntimeError, not a MemoryError)
OUT_OF_MEMORY = ("can't allocate memory", "not enough memory", "alloc_cpu.cpp", "CUDA out of memory")


class _Group(click.Group):
    """Turns RlsacError raised by any command into a one-line error with exit code 2 (an interrupted
    training: 130 / 143), and click's own usage errors (unknown option or command, bad choice, a file where a
    folder is expected) into the same one ``error:`` line instead of click's four-line usage block."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        try:
            code = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except click.exceptions.NoArgsIsHelpError as e:  # a bare `rlsac`: the help, as `rlsac --help`
            click.echo(e.ctx.get_help())
            sys.exit(0)
        except click.UsageError as e:
            where = e.ctx.command_path if e.ctx is not None else (prog_name or "rlsac")
            click.echo(f"error: {' '.join(e.format_message().split())} (`{where} --help` lists the options)",
                       err=True)
            sys.exit(2)
        except click.ClickException as e:
            e.show()
            sys.exit(e.exit_code)
        except click.exceptions.Abort:
            click.echo("error: aborted", err=True)
            sys.exit(1)
        sys.exit(code if isinstance(code, int) else 0)

    def invoke(self, ctx):
        from rlsac.signals import interrupt_on_signals

        try:
            numerics.check_mode()  # an unknown RLSAC_NUMERICS, or pins that did not take: before any work
            with interrupt_on_signals():  # SIGINT / SIGTERM: runs end KILLED, temp files go, exit 130 / 143
                return super().invoke(ctx)
        except RlsacError as e:
            raise _UserError(" ".join(str(e).split()) or e.__class__.__name__, getattr(e, "exit_code", 2)) from None
        except (MemoryError, RuntimeError) as e:  # sizes within their ranges that this machine cannot hold
            if not isinstance(e, MemoryError) and not any(m in str(e) for m in OUT_OF_MEMORY):
                _raise_signalled(e)
            first = " ".join(str(e).split())[:160]
            raise _UserError(f"out of memory ({e.__class__.__name__}: {first}); lower the sizes you set (batch_size, "
                             "buffer_size, num_envs, samples, val_iterations, ...)", 2) from None
        except Exception as e:
            _raise_signalled(e)


def _raise_signalled(e: Exception) -> None:
    """Re-raise ``e``, as the one-line interruption it wraps where a signal's ``Interrupted`` landed inside a library
    call that wrapped it (MLflow's database commit: issue #64), else as it is."""
    from rlsac.signals import interrupted_in

    signalled = interrupted_in(e)
    if signalled is None:
        raise e
    raise _UserError(str(signalled), signalled.exit_code) from None


class _TaskChoice(click.Choice):
    """--task: the names registered in rlsac.tasks.TASKS, read when first needed (importing the tasks
    imports torch, which ``rlsac --help`` should not wait for)."""

    def __init__(self) -> None:
        super().__init__([])

    @property
    def choices(self):
        from rlsac.tasks import task_names

        return task_names()

    @choices.setter
    def choices(self, value) -> None:
        pass


def task_option(f):
    return click.option("--task", type=_TaskChoice(), required=True, help="A registered task (rlsac.tasks).")(f)


def tracking_option(f):
    return click.option("--tracking/--no-tracking", default=True, show_default=True,
                        help="Log an MLflow run (MLFLOW_TRACKING_URI, default sqlite:///mlflow.db).")(f)


def device_option(f):
    return click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default="auto", show_default=True,
                        help="auto = cuda if available, else cpu.")(f)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="rlsac")
def cli() -> None:
    """RLSAC reproduction workbench: data, training, evaluation, ablations and figures."""
    # MLflow configures its logger at import time from this variable; its INFO lines are noise here.
    os.environ.setdefault("MLFLOW_LOGGING_LEVEL", "WARNING")


@cli.command("synth-lines")
@click.option("--outlier", "outlier_rate", type=float, help="Outlier rate rho in [0, 1). [default: 0.5]")
@click.option("--n-instances", type=int, help="Number of instances. [default: 1000]")
@click.option("--n-points", type=int, help="Points per instance N. [default: 100]")
@click.option("--picture-size", type=float, help="Side of the square picture. [default: 10]")
@click.option("--band", type=float, help="Inlier half-width around the line. [default: calibrated]")
@click.option("--line", type=click.Choice(["two_points", "point_angle", "angle_offset"]),
              help="How the ground-truth line is drawn.")
@click.option("--inlier-count", type=click.Choice(["fixed", "binomial"]), help="Inliers per instance.")
@click.option("--extent", type=click.Choice(["chord", "segment"]), help="Where inliers lie along the line.")
@click.option("--seed", type=int, help="Generator seed. [default: 0]")
@click.option("--out", type=click.Path(dir_okay=False),
              help="Output h5 [default: data/lines/lines_o{rate}_s{seed}.h5].")
@click.option("--params", "params_path", default="params.yaml", show_default=True,
              help="params.yaml whose lines_data section overrides the generator defaults.")
@tracking_option
def synth_lines(tracking: bool, params_path: str, **options) -> None:
    """Generate a synthetic 2D-line data set (paper Sec. 4.2)."""
    from rlsac.commands import synth_lines as run

    s = run(options, track=tracking, params_path=params_path)
    click.echo(f"wrote {s['path']}: {s['n_instances']} instances x {s['n_points']} points, "
               f"outlier rate {s['conf']['outlier_rate']:g}, inlier fraction {s['inlier_fraction']:.3f}, "
               f"seed {s['conf']['seed']}")


@cli.command("lines-data")
@click.option("--rate", type=float, required=True, help="Outlier rate.")
@click.option("--splits", default="train,val,test", show_default=True, help="Comma-separated splits.")
@click.option("--out-dir", default="data/lines", show_default=True, type=click.Path(file_okay=False))
@click.option("--params", "params_path", default="params.yaml", show_default=True,
              help="params.yaml: the lines protocol (n_<split>, seed_<split>) and lines_data.")
@tracking_option
def lines_data(tracking: bool, params_path: str, **options) -> None:
    """The line experiment's train/val/test files for one outlier rate (seed_<split> + round(10 rate))."""
    from rlsac.commands import lines_protocol_data as run

    s = run(options, track=tracking, params_path=params_path)
    click.echo(f"wrote {', '.join(s['files'])} (seeds {s['seeds']})")


@cli.command("import-scenes")
@click.option("--src", type=click.Path(file_okay=False),
              help="Source scenes (Strecha layout). [default: data/strecha]")
@click.option("--out", type=click.Path(file_okay=False),
              help="Output tutorial-layout root. [default: data/raw/strecha]")
@click.option("--split", help="Split folder written under --out. [default: all]")
@click.option("--scenes", help="Comma-separated scene names. [default: every scene]")
@click.option("--max-features", type=int, help="SIFT keypoints per image. [default: 8000]")
@click.option("--rootsift/--no-rootsift", default=None, help="RootSIFT descriptors. [default: on]")
@click.option("--min-matches", type=int, help="Drop pairs with fewer good matches. [default: 100]")
@click.option("--matches", help="Each pair's matches from this shipped file (written by --write-matches) instead of "
                                "SIFT; '' extracts them. [default: '']")
@click.option("--write-matches", type=click.Path(dir_okay=False),
              help="Also pack the extracted matches into this file, for --matches on another machine.")
@click.option("--set", "sets", multiple=True, metavar="KEY=VALUE", help="Other ImportConf field; repeatable.")
@tracking_option
def import_scenes(tracking: bool, sets: tuple[str, ...], write_matches: str | None, **options) -> None:
    """Import real scenes offline into the CVPR 2020 tutorial layout (rlsac.data.scenes)."""
    from rlsac.commands import import_scenes as run
    from rlsac.config import parse_sets

    _echo_result(run({**options, **parse_sets(sets)}, track=tracking, write_matches=write_matches))


@cli.command("prepare-cvpr2020")
@click.option("--root", type=click.Path(file_okay=False),
              help="Tutorial-layout root (CVPR 2020 RANSAC tutorial or import-scenes output). "
                   "[default: data/raw/strecha]")
@click.option("--split", help="Split folder under --root. [default: all]")
@click.option("--scenes", help="Comma-separated scene names. [default: every scene]")
@click.option("--n-points", type=int, help="Correspondences kept per pair. [default: 150]")
@click.option("--max-pairs-per-scene", type=int, help="Cap on pairs per scene, 0 = all. [default: 0]")
@click.option("--out", type=click.Path(dir_okay=False), help="Output h5. [default: data/fundamental/val.h5]")
@click.option("--set", "sets", multiple=True, metavar="KEY=VALUE", help="Other PrepareConf field; repeatable.")
@tracking_option
def prepare_cvpr2020(tracking: bool, sets: tuple[str, ...], **options) -> None:
    """Prepare fundamental-matrix pairs from the CVPR 2020 tutorial layout (rlsac.data.tutorial)."""
    from rlsac.commands import prepare_cvpr2020 as run
    from rlsac.config import parse_sets

    _echo_result(run({**options, **parse_sets(sets)}, track=tracking))


@cli.command()
@task_option
@click.option("--data", type=click.Path(dir_okay=False), help="Training h5.")
@click.option("--val-data", type=click.Path(dir_okay=False), help="Validation h5.")
@click.option("--out", type=click.Path(dir_okay=False), help="Checkpoint path, e.g. checkpoints/NAME.pt.")
@click.option("--method", type=click.Choice(["rlsac", "ngransac"]),
              help="rlsac = SAC-Discrete (the paper); ngransac = NG-RANSAC's network and training (rlsac.rl.ngransac, "
                   "options ngransac.*) [default: params.yaml, else rlsac].")
@click.option("--resume", is_flag=True, default=None, help="Resume from --out if it exists (rlsac only).")
@click.option("--seed", type=int)
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), help="auto = cuda if available.")
@click.option("--params", "params_path", default="params.yaml", show_default=True,
              help="params.yaml; its train.<task> section gives the defaults.")
@click.option("--set", "sets", multiple=True, metavar="KEY=VALUE",
              help="Override a TrainConf field, e.g. --set sac.actor_lr=1e-4.")
@tracking_option
def train(task: str, tracking: bool, params_path: str, sets: tuple[str, ...], **flags) -> None:
    """Train an RLSAC policy (rlsac.evaluation.train) or an NG-RANSAC network (--method ngransac)."""
    from rlsac.commands import train as run
    from rlsac.commands import train_options

    _echo_result(run(train_options(task, flags, sets, params_path), track=tracking))


@cli.command()
@task_option
@click.option("--method", type=click.Choice(list(METHODS)), required=True,
              help="oracle = refinement on the true inliers (synthetic lines); uniform / guided = the RLSAC "
                   "environment with uniform sets / sets drawn by SNN ratio (two-view tasks); opencv_ransac, usac, "
                   "usac_accurate, magsac, prosac = OpenCV's estimator of the task (prosac on SNN-ordered matches); "
                   "ngransac = our RANSAC with sets drawn by a trained NG-RANSAC network (--checkpoint); "
                   "*-lo = with local optimisation (params.yaml evaluate.<task>.lo).")
@click.option("--data", type=click.Path(dir_okay=False), required=True, help="Test h5.")
@click.option("--checkpoint", type=click.Path(dir_okay=False),
              help="Trained checkpoint (methods rlsac, rlsac-lo: RLSAC's; ngransac, ngransac-lo: NG-RANSAC's).")
@click.option("--iterations", type=int, help="Hypotheses per instance [default: params.yaml evaluate.<task>].")
@click.option("--steps-per-episode", type=int, help="RLSAC episode length [default: checkpoint's, else 15].")
@click.option("--sampling", type=click.Choice(["max", "prob"]), help="RLSAC test-time sampling [default: max].")
@click.option("--policy-every", type=int, help="RLSAC: recompute the policy every N steps, reusing its logits "
                                               "in between (not in the paper; reports/speed.md) [default: 1].")
@click.option("--sets-per-step", type=int, help="RLSAC / uniform / guided: minimal sets drawn and scored per "
                                                "episode step, one network call for all (not in the paper; "
                                                "reports/speed.md) [default: params.yaml, else 1].")
@click.option("--confidence", type=float, help="RLSAC / uniform / guided: stop an instance at RANSAC's termination "
                                               "bound for this confidence, 0 = use the whole budget (not in the "
                                               "paper) [default: params.yaml, else 0].")
@click.option("--threshold-px", type=float, help="Two-view tasks: inlier threshold in pixels, as tuned per fold "
                                                "(reports/tuning/) [default: the task's own threshold].")
@click.option("--prefilter", type=float, help="Two-view tasks: drop matches whose SNN ratio is above this before "
                                              "fitting, as tuned per fold [default: none].")
@click.option("--tuning", type=click.Path(dir_okay=False),
              help="A tuning record, reports/tuning/<task>/<regime>/<fold>/<row>.json: its chosen settings "
                   "(threshold, pre-filter, the row's own knobs), so that a fold cell of Table 2 / E is reproduced "
                   "by hand; it must be of this --task, --method and --checkpoint.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--batch-size", type=int, default=256, show_default=True)
@click.option("--threads", type=int, help="torch CPU threads on cpu, 0 = torch's default [default: 1, the fastest "
                                          "here: rlsac.evaluation.evaluate.THREADS].")
@click.option("--out-dir", type=click.Path(file_okay=False), help="[default: reports/eval/<name>]")
@click.option("--params", "params_path", default="params.yaml", show_default=True,
              help="params.yaml; its evaluate.<task> section gives the defaults.")
@device_option
@tracking_option
def evaluate(tracking: bool, params_path: str, **options) -> None:
    """Evaluate a method on a data file: errors CSV + summary JSON + MLflow run."""
    from rlsac.config import read_params, section
    from rlsac.evaluation.evaluate import check_options, format_summary
    from rlsac.evaluation.evaluate import evaluate as run

    params = read_params(params_path)
    defaults = section(params, "evaluate", options["task"])
    record = options.pop("tuning")
    given = {k: v for k, v in options.items() if v is not None}
    if record is not None:
        from rlsac.evaluation.tune import record_options

        tuned = record_options(record, options["task"], options["method"], options["checkpoint"], defaults.get("lo"))
        both = sorted(k for k in tuned if k in given and k in ("threshold_px", "prefilter"))
        if both:  # which one wins would be a guess: refuse
            raise RlsacError(f"--tuning {record} sets {both[0]}; give --{both[0].replace('_', '-')} or --tuning, "
                             "not both")
        # then against the data it would set: budget, regime, fold and scenes (issue #64: another fold's record ran)
        record_options(record, options["task"], options["method"], options["checkpoint"], defaults.get("lo"),
                       options["data"], params, options.get("iterations") or defaults.get("iterations"))
        defaults = {**defaults, **tuned}
    # the one options object of this evaluation, checked here; read by attribute from here to the estimator
    o = check_options({**defaults, **given})
    click.echo(format_summary(run(o, track=tracking)))


@cli.command()
@click.option("--what", type=click.Choice(["descriptors", "sampling", "points", "all", "generalisation"]),
              required=True, help="Table 3 (a) descriptors, (b) sampling, (c) points, all three, or Ours-0.5.")
@click.option("--stage", type=click.Choice(["all", "train", "evaluate"]), default="all", show_default=True,
              help="train missing models, evaluate, rebuild Table 3 (all); or only one of the two.")
@click.option("--variants", help="Comma-separated variants of the study [default: all of them].")
@click.option("--force", is_flag=True, default=None, help="Retrain models whose checkpoint exists.")
@click.option("--train-steps", type=int, help="Override sac.total_steps of every model trained.")
@click.option("--full", is_flag=True, default=None,
              help="The record's size: the study's fold stages (every fold, every seed) through `rlsac pipeline`, "
                   "then its Table 3 under --out. Default: the quick study on one fold (descriptors, sampling).")
@click.option("--fold", help="The quick study's fold. [default: fountain, the smallest]")
@click.option("--iterations", type=int, help="The quick study's budget. [default: 1000, Table 2's]")
@click.option("--out", help="Where the quick study's results and table go. [default: scratch/ablate]")
@click.option("--workers", type=int, help="--full: stages at once (rlsac pipeline). [default: the cores]")
@click.option("--params", "params", default="params.yaml", show_default=True,
              help="params.yaml: train.fundamental, ablation and lines sections.")
@click.option("--set", "sets", multiple=True, metavar="KEY=VALUE",
              help="Other option (threads, models, data_dir, ckpt_dir, eval_dir, table); repeatable.")
@device_option
@tracking_option
def ablate(tracking: bool, sets: tuple[str, ...], **options) -> None:
    """Run one ablation study of Table 3 and print its table (rlsac.experiments.ablate): by default, quickly, on one
    fold with the committed models (rlsac.experiments.quick); --full at the record's size."""
    from rlsac.config import parse_sets
    from rlsac.experiments.ablate import ablate as run
    from rlsac.experiments.ablate import format_summary

    click.echo(format_summary(run({**options, **parse_sets(sets)}, track=tracking)))


@cli.command()
@click.option("--stage", type=click.Choice(["data", "pool", "train", "tune", "evaluate", "select", "retune"]),
              required=True,
              help="data: prepare the fold's train/val/test files; pool: its training pairs with the model regime's "
                   "pool of matches each (data/folds/pool/<fold>.h5, the episodes of folds.pool_models); train: its "
                   "RLSAC models; tune: choose every row's "
                   "settings on the fold's val.h5 (reports/tuning/); evaluate: every row at every budget on test.h5 "
                   "with its tuned settings; select: replay a model's training and test every validated actor "
                   "(reports/selection/); retune: re-choose --only's settings on bootstrap resamples of val.h5 and "
                   "test each choice (reports/retune/, params tuning_budget).")
@click.option("--regime", help="Data regime, a key of params.yaml folds.pool (e.g. easy, hard); required but with "
                               "--stage pool (the model regime's).")
@click.option("--fold", required=True, help="Test building, one of params.yaml folds.test (e.g. castle).")
@click.option("--model", help="With --stage train: one model of folds.models, ablation_models or the N study's "
                              "<model>-n<N> [default: all of them]; with --stage select: a model of "
                              "folds.select_models or <model>-s<seed>.")
@click.option("--points", type=click.IntRange(min=8), help="With --stage data: N points per pair, one of params.yaml "
                                                             "folds.points (Table 3 c; data/folds/<regime>-n<N>).")
@click.option("--task", type=click.Choice(["fundamental", "essential"]), default="fundamental", show_default=True,
              help="With --stage tune or evaluate: the fundamental matrix (Table 2, params folds) or the essential "
                   "matrix (Table E, params essential) on the fold data.")
@click.option("--only", help="With --stage tune or evaluate: comma-separated rows (methods, models, <model>-lo, "
                             "<row>-fast, <row>-n<N>) [default: all].")
@click.option("--tune-iterations", type=int,
              help="With --stage tune or evaluate: tune at this budget instead of tuning.iterations, and test at it "
                   "alone (a budget of folds.iterations; reports/tuning_at<N>/, reports/eval/folds_at<N>/).")
@click.option("--params", "params", default="params.yaml", show_default=True,
              help="params.yaml: its folds, fundamental and train.fundamental sections.")
@click.option("--threads", type=int, default=1, show_default=True, help="torch CPU threads (1 is fastest here).")
@device_option
@tracking_option
def folds(tracking: bool, **options) -> None:
    """Leave-one-building-out benchmark (fundamental or essential matrix), one stage of one fold
    (rlsac.experiments.folds)."""
    from rlsac.experiments.folds import folds as run
    from rlsac.experiments.folds import format_summary

    click.echo(format_summary(run(options, track=tracking)))



@cli.command()
@click.option("--stage", type=click.Choice(SCALE_STAGES), required=True,
              help="pool: the fold's training pairs with the pool's points each (data/scale/<fold>/pool.h5); train: "
                   "one run of an arm and seed with its step snapshots; evaluate: every snapshot on the fold's test "
                   "pairs at scale.iterations (evaluate-final: those of scale.final_steps at scale.final_iterations; "
                   "validate: every snapshot on the fold's validation pairs, what chooses the recipe); control: the "
                   "learner's positive control on synthetic pairs; fit: the synthetic generator's statistics fitted "
                   "to the fold's training pairs, beside its own (reports/synthetic_fit.json); synthetic: the "
                   "pretrain arm's synthetic pairs (data/scale/<fold>/synthetic.h5); ladder: one run of the learner's "
                   "ladder (issue #61, rlsac.experiments.ladder: --arm the rung, --seed a seed of params "
                   "ladder.seeds; without --seed the rung's "
                   "uniform, guided and oracle samplers).")
@click.option("--arm", help="With train / evaluate: fixed (the training file's points), redraw (a fresh draw of the "
                            "pool per episode, images swapped at random), pretrain (synthetic pairs first, then "
                            "redraw's episodes) or prefilter (redraw's episodes pre-filtered as at test).")
@click.option("--seed", type=int, help="With train / evaluate: a training seed of params.yaml scale.seeds.")
@click.option("--params", "params", default="params.yaml", show_default=True,
              help="params.yaml: its scale, folds, fundamental and train.fundamental sections.")
@click.option("--threads", type=int, default=1, show_default=True, help="torch CPU threads (1 is fastest here).")
@device_option
@tracking_option
def scale(tracking: bool, **options) -> None:
    """The training-scale study (issue #46): one fold trained at growing scale, four data arms
    (rlsac.experiments.scale)."""
    from rlsac.experiments.scale import format_summary
    from rlsac.experiments.scale import scale as run

    click.echo(format_summary(run(options, track=tracking)))

@cli.command()
@click.option("--checkpoint", required=True, type=click.Path(dir_okay=False),
              help="An RLSAC checkpoint whose training is replayed (its own options, data and seed).")
@click.option("--data", required=True, type=click.Path(dir_okay=False), help="Test h5 every validated actor runs on.")
@click.option("--kept-eval", required=True, type=click.Path(file_okay=False),
              help="The checkpoint's own evaluation on --data (errors.csv, summary.json): the replayed kept actor "
                   "must give its mAA.")
@click.option("--out", required=True, help="Output stem: writes <out>.csv and <out>.json (e.g. "
                                           "reports/selection/lines/o0.7-s1).")
@click.option("--iterations", type=int, help="Hypotheses per instance [default: params.yaml evaluate.<task>].")
@click.option("--tie", type=float, help="Validation scores within this of the kept one's count as tied [0.005].")
@click.option("--params", "params_path", default="params.yaml", show_default=True,
              help="params.yaml: its evaluate.<task> section gives the test settings.")
@device_option
@tracking_option
def select(tracking: bool, params_path: str, **options) -> None:
    """Checkpoint selection measured: replay a model's training and test every validated actor
    (rlsac.experiments.selection)."""
    from rlsac.config import read_params
    from rlsac.experiments.selection import select_checkpoint

    s = select_checkpoint(options, read_params(params_path), track=tracking)
    tests = ", ".join(f"{k}: {v.get('mAA', float('nan')):.4f}" for k, v in s["test"].items())
    click.echo(f"select: kept step {s['kept_step']}, last {s['last_step']}; test mAA by step {{{tests}}}; "
               f"wrote {', '.join(s['files'])}")


@cli.command()
@click.option("--which", type=click.Choice(["1", "2", "3", "iterations", "folds", "essential", "claims", "paper",
                                           "selection", "scale", "tuning-budget", "learner", "all"]),
              default="all", show_default=True,
              help="Table 1 (lines), 2 (fundamental), 3 (ablations), the iterations CSV, Table 2 over the "
                   "leave-one-building-out folds, Table E (essential matrix, not in the paper), reports/claims.md "
                   "(every claim against its seed-aware interval), reports/paper.md (the paper's claims beside ours, "
                   "one verdict each), reports/selection.md (kept vs last checkpoint), reports/scale.md (the "
                   "training-scale study, issue #46; not in all), reports/tuning_budget.md (tuning at the test "
                   "budget and re-tuning variance, issue #47; not in all), reports/learner.md (where the learner "
                   "stops: the ladder, issue #61; not in all), or all.")
@click.option("--eval-root", default="reports/eval", show_default=True, type=click.Path(file_okay=False),
              help="Root of the evaluation summaries (lines/, fundamental/, ablation/).")
@click.option("--out-dir", default="reports", show_default=True, type=click.Path(file_okay=False))
@tracking_option
def table(tracking: bool, **options) -> None:
    """Build the paper's tables from evaluation summaries, beside the paper's numbers (rlsac.reports.tables)."""
    from rlsac.reports.tables import build

    s = build(options, track=tracking)
    click.echo(f"wrote {s['files']}")
    if s["n_missing"]:
        click.echo(f"{s['n_missing']} result file(s) missing (shown as –)")


# the keys of rlsac.reports.figures.DEFAULTS (test_cli checks the two agree): the figures module loads torch and
# matplotlib, too slow to import for `rlsac --help`
PLOT_KEYS = ("which=all|folds|curves|essential|line|pair|steps|iterations (comma list; folds: pooled fold mAA vs "
             "budget, curves: the fold models' validation curves, essential: Table E's mAA vs budget, line / pair / "
             "steps: one instance step by step, iterations: the retired split's budgets); out_dir=reports/figures; "
             "folds_iterations_csv, essential_iterations_csv, folds_checkpoints, eval_root, reports_dir, "
             "iterations_csv (inputs); line_data, line_checkpoint, line_index=auto, line_steps=6; fundamental_data, "
             "fundamental_checkpoint, pair=auto, image_root, fundamental_iterations=1000, fundamental_steps=6; "
             "seed=0, device=cpu")


@cli.command()
@click.option("--set", "sets", multiple=True, metavar="KEY=VALUE", help="Option; repeatable. Keys: " + PLOT_KEYS)
@tracking_option
def plot(tracking: bool, sets: tuple[str, ...]) -> None:
    """Draw the report figures into reports/figures (rlsac.reports.figures), e.g. --set which=folds,curves."""
    from rlsac.config import parse_sets
    from rlsac.reports.figures import plot as run

    _echo_result(run(parse_sets(sets), track=tracking))


@cli.command()
@click.option("--host", default="127.0.0.1", show_default=True, help="Address the UI listens on.")
@click.option("--port", type=click.IntRange(1, 65535), default=5000, show_default=True, help="Port of the UI.")
@click.option("--links-only", is_flag=True, help="Print the links, start no server.")
def ui(host: str, port: int, links_only: bool) -> None:
    """The MLflow UI on the tracking store (MLFLOW_TRACKING_URI, default sqlite:///mlflow.db), after one link per
    experiment that opens its runs table with the mAA columns (MLflow 3's UI lands on GenAI pages otherwise)."""
    import os
    import sys

    from rlsac.tracking import DEFAULT_URI, runs_links, store_path

    uri = os.environ.get("MLFLOW_TRACKING_URI", DEFAULT_URI)
    db = store_path(uri)
    if db is not None and not db.is_file():
        raise RlsacError(f"{db}: no tracking store here (an rlsac command with tracking makes it; "
                         "MLFLOW_TRACKING_URI names another)")
    links = runs_links(uri, f"http://{'127.0.0.1' if host in ('0.0.0.0', '::') else host}:{port}")
    for e in links:
        click.echo(f"{e['name']:<12} {e['runs']:>5} runs  {e['url']}")
    if not links:
        click.echo(f"{uri}: no runs yet")
    if links_only:
        return
    click.echo("open a link above (the UI's own front page is MLflow's welcome page); Ctrl-C stops the UI", err=True)
    sys.stdout.flush()
    os.execv(sys.executable, [sys.executable, "-m", "mlflow", "ui", "--backend-store-uri", uri, "--host", host,
                              "--port", str(port)])


@cli.command("quick")
@click.option("--fold", help="The fold whose test pairs are used. [default: fountain, the smallest]")
@click.option("--regime", type=click.Choice(["easy", "hard"]), help="The data regime. [default: hard]")
@click.option("--iterations", type=int, help="Hypotheses per pair. [default: 1000, Table 2's]")
@click.option("--out", help="Results and table.md. [default: scratch/quick]")
@click.option("--params", "params", default="params.yaml", show_default=True, help="params.yaml: the folds section.")
@tracking_option
def quick_cmd(tracking: bool, **options) -> None:
    """The workbench's answer in minutes: the committed RLSAC model against uniform sets, OpenCV's RANSAC and
    MAGSAC++ on one fold's test pairs, a table with paired intervals (rlsac.experiments.quick)."""
    from rlsac.experiments.quick import format_summary, quick

    click.echo(format_summary(quick(options, track=tracking)))


@cli.command("calibrate-lines")
@click.option("--n-instances", type=int, default=1000, show_default=True)
@click.option("--seed", type=int, default=123, show_default=True, help="First data seed.")
@click.option("--n-seeds", type=int, default=12, show_default=True,
              help="Data seeds seed..seed+n-1; the row is their mean, with the seed-to-seed spread.")
@click.option("--iterations", type=int, default=150, show_default=True)
@click.option("--out", default="reports/calibration_lines", show_default=True, help="Output stem (.md and .csv).")
@click.option("--params", "params_path", default="params.yaml", show_default=True,
              help="params.yaml whose lines_data section overrides the generator defaults.")
@device_option
@tracking_option
def calibrate_lines(tracking: bool, params_path: str, **options) -> None:
    """Our 150-iteration RANSAC on the default line sets vs the paper's RANSAC row (Table 1)."""
    from rlsac.commands import calibrate_lines as run

    s = run(options, track=tracking, params_path=params_path)
    click.echo(s["table"].to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    click.echo(f"wrote {s['md']} and {s['csv']}")


@cli.command()
@click.option("--stages", help="Comma-separated stage addresses, foreach names or fnmatch patterns "
                               "(e.g. 'fold_eval@hard-*') [default: every committed stage].")
@click.option("--sample", type=int, help="Verify N stages drawn at random from those selected.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of --sample.")
@click.option("--include-train", is_flag=True, help="Also training stages (minutes to hours each).")
@click.option("--scratch", type=click.Path(file_okay=False),
              help="Scratch folder, absent or empty [default: a new folder in the system temp dir].")
@click.option("--keep", is_flag=True, help="Keep the scratch folder (re-run outputs, logs/<stage>.log).")
@click.option("--repo", default=".", show_default=True, type=click.Path(file_okay=False),
              help="The DVC repository to verify.")
@click.option("--tolerance", type=float,
              help="Also accept outputs that agree by value: JSON numbers within this much, CSV numbers not "
                   "compared (another numeric platform; such a stage is 'close').")
@click.option("--workers", type=click.IntRange(min=1), default=1, show_default=True,
              help="Stages re-run at once (two that read or write one another's outputs never do).")
@click.option("--platform", "platform_only", is_flag=True,
              help="Only compare this machine's numeric platform with the record's (reports/platform.json); "
                   "exit 1 when they differ.")
@tracking_option
def verify(tracking: bool, platform_only: bool, **options) -> None:
    """Re-run committed pipeline stages in a scratch copy and compare every output byte for byte
    (rlsac.runners.verify); exit 1 when one differs or fails (or, with --tolerance, is not even close)."""
    from rlsac.runners.verify import format_summary
    from rlsac.runners.verify import verify as run

    if platform_only:
        given = [k for k in ("stages", "sample", "tolerance", "scratch") if options.get(k) is not None] + [
            k for k in ("include_train", "keep") if options.get(k)] + (["seed"] if options.get("seed") else []) + (
            ["workers"] if options.get("workers", 1) != 1 else [])
        if given:
            raise RlsacError(f"--platform only compares platforms; it takes no --{given[0].replace('_', '-')}")
        platform = numerics.compare(options["repo"], required=True)
        click.echo("\n".join(numerics.report_lines(platform)))
        sys.exit(1 if platform["differences"] else 0)

    def note() -> None:  # after the options and inputs were checked: a user error prints nothing else
        platform = numerics.compare(options["repo"], required=False)
        if platform and platform["differences"]:
            click.echo(f"note: this machine's numeric platform is not the record's "
                       f"({'; '.join(platform['differences'])}): its bytes are not expected to match "
                       f"(reports/platform.md)")

    s = run(options, track=tracking, report=click.echo, checked=note)
    click.echo(format_summary(s))
    if s["n_identical"] + s["n_close"] != s["n_stages"]:
        sys.exit(1)


@cli.command()
@click.argument("stages", nargs=-1)
@click.option("--repo", default=".", show_default=True, type=click.Path(file_okay=False),
              help="The DVC repository (e.g. experiments/quick for the quick profile).")
@click.option("--workers", type=click.IntRange(min=1),
              help="CPUs of the local Ray cluster, stages run at once [default: the number of cores].")
@click.option("--address", help="Join this Ray cluster (`ray start --head` prints it, or 'auto') instead of "
                                "starting a local one.")
@click.option("--gpus-per-train", type=click.FloatRange(min=0), default=0.0, show_default=True,
              help="GPUs a training stage asks Ray for (0 = none; e.g. 1, or 0.5 to share one).")
@click.option("--gpu-stages", default="*train*", show_default=True,
              help="Comma-separated fnmatch patterns of the stages --gpus-per-train applies to.")
@click.option("--dry-run", is_flag=True, help="Print which stages would run; run nothing.")
@click.option("--runner", type=click.Choice(["direct", "dvc"]), default="direct", show_default=True,
              help="direct: a task runs the stage's command and this command writes dvc.lock (one writer, atomic); "
                   "dvc: a task runs `dvc repro -s <stage>`.")
@click.option("--remote", help="Nodes share no disk: each stage's inputs and outputs travel through this S3 bucket "
                               "(s3://bucket/prefix, or a DVC remote's name; endpoint and credentials from the AWS_* "
                               "environment variables or the DVC remote's config).")
@click.option("--retries", type=click.IntRange(min=0), default=2, show_default=True,
              help="Runs again of a stage whose Ray worker or node died (a stage is idempotent: its outputs are "
                   "removed before its command runs); a stage whose command failed is not run again.")
@click.option("--recover", is_flag=True,
              help="Only repair what a killed (SIGKILL) run left: put back the outputs it had set aside, end its "
                   "local Ray cluster's leftover processes (every run does this first).")
@tracking_option
def pipeline(tracking: bool, stages: tuple[str, ...], recover: bool, **options) -> None:
    """Run the DVC pipeline's out-of-date stages (or STAGES: names, foreach groups or patterns, with what they
    need) as Ray tasks in dependency order, each its own command, recorded in dvc.lock as `dvc repro` records it
    (rlsac.runners.pipeline and its parts, rlsac.runners.dvc_stage); exit 1 when one fails."""
    from rlsac.errors import Interrupted
    from rlsac.runners.pipeline import pipeline as run
    from rlsac.runners.recovery import format_recovery
    from rlsac.runners.summary import format_summary

    if recover:
        from rlsac.runners.recovery import recover as repair

        if stages or options["dry_run"]:
            raise RlsacError(f"--recover only repairs a killed run; it takes no {'STAGES' if stages else '--dry-run'}")
        click.echo(format_recovery(repair(options["repo"], required=True)) or "pipeline: nothing to recover")
        return
    try:
        # an empty STAGES argument ('') names no stage: it is not "every stage" (issue #49)
        s = run({**options, "stages": ",".join(stages) if stages else None}, track=tracking)
    except Interrupted as e:  # what ran before the signal, then the one error line
        if getattr(e, "summary", None):
            click.echo(format_summary(e.summary))
        raise
    click.echo(format_summary(s))
    if s["counts"].get("failed"):
        sys.exit(1)


def _echo_result(result) -> None:
    if result is None:
        return
    if isinstance(result, dict):
        click.echo(", ".join(f"{k}={v}" for k, v in result.items() if not isinstance(v, (dict, list))))
    else:
        click.echo(str(result))


def main(argv: list[str] | None = None) -> None:
    """Console entry point (``rlsac``)."""
    cli.main(args=argv, prog_name="rlsac")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
