"""What a killed driver leaves, repaired: its Ray session's processes ended, the set-aside outputs of
its stages put back (rlsac.runners.dvc_stage.recover)."""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path

from rlsac.errors import RlsacError
from rlsac.runners.stage_task import KILL_GRACE_S
from rlsac.runners.summary import _names

DRIVERS = Path(".dvc") / "tmp" / "rlsac-drivers"  # under the repository's root: <pid>.json of each running driver


def _note_driver(root: Path, ray) -> Path | None:
    """The local Ray cluster this driver started, by its session's name (in the command line of each of its
    processes), in ``DRIVERS``: if the driver is SIGKILLed, ``recover`` ends what of the cluster outlived it (Ray's
    agents did). -> the note's path, removed when the driver ends; None when Ray does not say its session."""
    from rlsac.runners.dvc_stage import _owner, write_atomic

    try:
        session = Path(ray._private.worker._global_node.get_session_dir_path()).name
    except Exception:  # noqa: BLE001 (Ray's internals moved: nothing to note, nothing ended later)
        return None
    path = root / DRIVERS / f"{os.getpid()}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, json.dumps({"owner": _owner(), "session": session}))
    return path


def _end_session(session: str) -> int:
    """End (SIGTERM, then SIGKILL after 5 s) this user's processes whose command line names the Ray session
    ``session``. -> how many there were."""
    import psutil

    me, user = os.getpid(), psutil.Process().username()
    procs = []
    for p in psutil.process_iter(["cmdline", "username"]):
        with contextlib.suppress(psutil.Error):
            if p.pid != me and p.info["username"] == user and session in " ".join(p.info["cmdline"] or []):
                p.terminate()
                procs.append(p)
    _, left = psutil.wait_procs(procs, timeout=5)
    for p in left:
        with contextlib.suppress(psutil.Error):
            p.kill()
    return len(procs)


def recover(repo: str | os.PathLike = ".", required: bool = False) -> dict:
    """What a SIGKILLed driver of this repository left, repaired: its local Ray cluster's processes that outlived it
    ended, then the outputs its stages had set aside put back (rlsac.runners.dvc_stage.recover). ``repo``: the
    repository or a folder in it (``required``: else an error; not: nothing to do). -> {"processes": how many were
    ended, "outputs": the paths restored, from the root}."""
    from rlsac.runners.dvc_stage import _alive
    from rlsac.runners.dvc_stage import recover as recover_outputs

    root = _dvc_root(repo)
    if root is None:
        if required:
            raise RlsacError(f"--repo {repo}: not in a DVC repository (no .dvc folder here or above)")
        return {"processes": 0, "outputs": []}
    ended = 0
    for note in sorted((root / DRIVERS).glob("*.json")) if (root / DRIVERS).is_dir() else []:
        try:
            driver = json.loads(note.read_text())
            if _alive(driver["owner"]):
                continue
            ended += _end_session(str(driver["session"]))
        except (OSError, ValueError, KeyError, TypeError):
            pass  # a note cut short or not ours: it goes
        note.unlink(missing_ok=True)
    # a dead worker's guard ends its stage's command within the grace: the outputs wait for that, no longer
    outputs = recover_outputs(root, wait_s=KILL_GRACE_S + 5.0)
    return {"processes": ended, "outputs": [os.path.relpath(p, root) for p in outputs]}


def _dvc_root(repo: str | os.PathLike) -> Path | None:
    """The DVC repository holding ``repo`` (the nearest folder with a .dvc folder, up from it), None outside one."""
    return next((d for d in (Path(repo).resolve(), *Path(repo).resolve().parents) if (d / ".dvc").is_dir()), None)


def format_recovery(r: dict) -> str | None:
    """One line of what ``recover`` did, None when there was nothing to do."""
    if not r["processes"] and not r["outputs"]:
        return None
    return (f"pipeline: a killed run's leftovers repaired: {len(r['outputs'])} set-aside outputs restored"
            + (f" ({_names(r['outputs'])})" if r["outputs"] else "")
            + f", {r['processes']} Ray processes of its cluster ended")


def _restore_interrupted(plan: dict, addresses) -> None:
    """The outputs of the stages an interruption stopped, as they were before them (rlsac.runners.dvc_stage.restore,
    once each stage's guard has ended its command): a cancelled worker cannot do it, and DVC's way (outputs deleted
    before the command) would leave committed files deleted. A --remote stage's outputs are on its node."""
    if plan.get("remote") is not None:
        return
    from rlsac.runners.dvc_stage import restore

    for a in addresses:
        if a in plan.get("specs", {}):
            restore(plan["root"], plan["specs"][a], wait_s=KILL_GRACE_S + 5.0)
