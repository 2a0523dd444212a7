"""The numeric platform a committed result was computed on, and whether this machine is the same one.

The same code, inputs and seed give the same bytes only on the same numeric code paths, and three of our
libraries choose theirs from the CPU at run time:
- MKL (torch's BLAS and LAPACK) by vendor as well as by instruction set: on a non-Intel CPU it takes a generic
  branch even where AVX-512 is there, so a matmul rounds differently from the same matmul on an Intel AVX-512 CPU;
- ATen's own kernels by instruction set (``torch.backends.cpu.get_cpu_capability()``);
- OpenCV (the Strecha import's SIFT) by instruction set, with approximate instructions (rsqrt) whose bits are the
  vendor's own.
``reports/platform.json`` records the platform the committed record was made on (how it was established:
reports/platform.md); ``rlsac verify --platform`` compares it with this machine's, and CI checks the record byte for
byte only where they match.
"""

from __future__ import annotations

import json
import os
import platform
import re
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path

from rlsac.errors import RlsacError

RECORD = "reports/platform.json"
# the fields that decide the bytes of a result; the others (models, versions) are there for the reader
KEYS = ("machine", "cpu_vendor", "mkl_branch", "aten_capability")
# MKL's verbose line names its code branch: "... for Intel(R) 64 architecture <branch>, Lnx ..."
_MKL_LINE = re.compile(r"for Intel\(R\) 64 architecture (.*?), Lnx")
_PROBE = "import torch; torch.ones(64, 64) @ torch.ones(64, 64)"


def mkl_family(branch: str) -> str:
    """MKL's branch text -> the instruction set its kernels use: 'AVX-512', 'AVX2', 'AVX', 'SSE4.2' or 'generic'
    (MKL's 'Intel(R) Architecture processors', what it runs on a CPU it does not take for Intel's)."""
    for family in ("AVX-512", "AVX2", "AVX", "SSE4.2"):
        if f"(Intel(R) {family})" in branch:
            return family
    return "generic" if "Architecture processors" in branch else "unknown"


def mkl_branch() -> str:
    """The branch MKL takes on this machine, from its verbose line (a child process: MKL prints it from C).
    '' where torch is not built with MKL or the line is not found."""
    import torch

    if not torch.backends.mkl.is_available():
        return ""
    try:
        out = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=120,
                             env={**os.environ, "MKL_VERBOSE": "1"}).stdout
    except (OSError, subprocess.SubprocessError):
        return ""
    m = _MKL_LINE.search(out)
    return m.group(1) if m else ""


def cpu_vendor() -> str:
    """'GenuineIntel', 'AuthenticAMD', ... from /proc/cpuinfo; platform.processor() elsewhere."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("vendor_id"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def describe() -> dict:
    """This machine's numeric platform: the KEYS plus what a reader wants beside them."""
    import cv2
    import numpy
    import torch

    branch = mkl_branch()
    return {"machine": platform.machine(), "cpu_vendor": cpu_vendor(),
            "mkl_branch": mkl_family(branch) if branch else "none", "aten_capability":
            torch.backends.cpu.get_cpu_capability(), "mkl_branch_text": branch,
            "opencv_dispatch": cv2.getCPUFeaturesLine(), "torch": torch.__version__, "numpy": numpy.__version__,
            "opencv": cv2.__version__}


@contextmanager
def portable_blas():
    """MKL on the branch that every x86-64 vendor runs alike (MKL_CBWR=COMPATIBLE: on the machine of
    reports/platform.md it gave the same bytes with MKL on its generic and on its Intel AVX-512 branch) for the MKL
    calls of a process that has made none yet: MKL reads the setting at its first call and keeps it. A value the user
    set is kept; the environment is put back on exit, so that later child processes do not inherit it.
    -> (as the context value) whether MKL_CBWR is COMPATIBLE inside."""
    old = os.environ.get("MKL_CBWR")
    os.environ.setdefault("MKL_CBWR", "COMPATIBLE")
    try:
        yield os.environ["MKL_CBWR"] == "COMPATIBLE"
    finally:
        if old is None:
            os.environ.pop("MKL_CBWR", None)
        else:
            os.environ["MKL_CBWR"] = old


def load_record(root: str | Path = ".") -> dict:
    """The record's platform (``reports/platform.json`` under ``root``); RlsacError when missing or malformed."""
    path = Path(root) / RECORD
    try:
        rec = json.loads(path.read_text())
    except OSError as e:
        raise RlsacError(f"{path}: cannot read the record's platform ({e.strerror or e})") from None
    except ValueError as e:
        raise RlsacError(f"{path}: not JSON ({e})") from None
    if not isinstance(rec, dict) or any(not isinstance(rec.get(k), str) for k in KEYS):
        raise RlsacError(f"{path}: needs the string keys {', '.join(KEYS)}")
    return rec


def differences(record: dict, here: dict) -> list[str]:
    """``key record -> here`` for every deciding key whose value differs (empty: the same platform)."""
    return [f"{k} {record[k]} -> {here[k]}" for k in KEYS if record[k] != here[k]]


def compare(root: str | Path = ".", required: bool = False) -> dict | None:
    """This machine's platform against the record's under ``root``: {"record", "here", "differences"}; None when
    the repository has no record of its platform (an RlsacError instead when ``required``)."""
    if not required and not (Path(root) / RECORD).exists():
        return None
    record = load_record(root)
    here = describe()
    return {"record": record, "here": here, "differences": differences(record, here)}


def report_lines(c: dict) -> list[str]:
    """``compare``'s result as lines: each deciding key, record beside here, then the verdict."""
    lines = [f"{k:<16} record {c['record'][k]:<14} here {c['here'][k]}" for k in KEYS]
    diff = c["differences"]
    return lines + [f"platform: differs ({'; '.join(diff)})" if diff else "platform: the record's"]

