"""The numeric platform a committed result was computed on, and whether this machine is the same one.

The same code, inputs and seed give the same bytes only on the same numeric code paths, and four of our
libraries choose theirs from the CPU at run time:
- MKL (torch's BLAS and LAPACK) by vendor as well as by instruction set: on a non-Intel CPU it takes a generic
  branch even where AVX-512 is there, so a matmul rounds differently from the same matmul on an Intel AVX-512 CPU;
- ATen's own kernels by instruction set (``torch.backends.cpu.get_cpu_capability()``);
- OpenCV (the Strecha import's SIFT) by instruction set, with approximate instructions (rsqrt) whose bits are the
  vendor's own; and the Intel IPP inside it (SIFT's exp and magnitude) by instruction set too, with its own CPUID
  dispatcher that OpenCV's switch does not reach (issue #63).
``reports/platform.json`` records the platform the committed record was made on (how it was established:
reports/platform.md); ``rlsac verify --platform`` compares it with this machine's, and CI checks the record byte for
byte only where they match.

Two numeric modes (``RLSAC_NUMERICS``): ``native`` lets each library take the code paths of this CPU (fastest; the
bytes are this platform's), ``portable`` pins every library to paths that every x86-64 CPU with AVX2 runs alike
(``PINS``; measured in reports/platform.md: MKL's vendor branch then reaches no output). ``apply_pins`` sets them
when ``rlsac`` is imported, before torch, numpy and OpenCV load, so every command and every pipeline stage runs
under the mode of the record.
"""

from __future__ import annotations

import functools
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
# the fields that decide the bytes of a native result; the others (models, versions) are there for the reader
KEYS = ("machine", "cpu_vendor", "mkl_branch", "aten_capability")
# under the pins the vendor and MKL's branch no longer decide (reports/platform.md); the mode and ATen's level do
PORTABLE_KEYS = ("machine", "numerics", "aten_capability")

ENV = "RLSAC_NUMERICS"
MODES = ("native", "portable")
DEFAULT_MODE = "portable"  # the mode the committed record was made in (reports/platform.json "numerics")
# numpy 2.4's dispatch targets above X86_V3 (AVX2); the pinned OpenCV's only one above AVX2 is AVX512-SKX
# (cv2.getCPUFeaturesLine()); OpenCV warns about disabling a feature the CPU lacks, so that pin is conditional
_NUMPY_AVX512 = "X86_V4 AVX512_ICL AVX512_SPR"
_OPENCV_AVX512 = "AVX512-SKX"
# Each library's code paths pinned to what every x86-64 CPU with AVX2 runs alike. Each is read once, when its
# library loads or makes its first call, which is why apply_pins runs at `import rlsac`.
PINS = {
    "MKL_CBWR": "COMPATIBLE",  # MKL: one branch for every vendor (its AVX-512 branch is Intel's only)
    "ATEN_CPU_CAPABILITY": "avx2",  # ATen's kernels at AVX2, which Intel and AMD CPUs of the last decade have
    "ONEDNN_MAX_CPU_ISA": "AVX2",  # oneDNN (torch's mkldnn ops) likewise
    "OPENBLAS_CORETYPE": "Haswell",  # numpy's OpenBLAS kernels: the AVX2 ones
    "NPY_DISABLE_CPU_FEATURES": _NUMPY_AVX512,  # numpy's own SIMD loops at AVX2
    # Intel IPP inside OpenCV (SIFT's exp and magnitude) picks its kernels from CPUID itself, past OPENCV_CPU_DISABLE:
    # its AVX-512 ones round otherwise than its AVX2 ones (issue #63; the record's bins: rlsac.data.sift_record)
    "OPENCV_IPP": "avx2",
}
# OpenCV's dispatched kernels at AVX2; only where the CPU has AVX-512 (pins() adds it)
OPENCV_PIN = ("OPENCV_CPU_DISABLE", _OPENCV_AVX512)


@functools.cache
def _cpuinfo() -> str:
    """/proc/cpuinfo ('' where there is none): read once, by the pins and by the platform's description."""
    try:
        return Path("/proc/cpuinfo").read_text()
    except OSError:
        return ""


def _has_avx512() -> bool:
    return " avx512f" in _cpuinfo()


def pins() -> dict[str, str]:
    """The portable mode's environment on this machine: PINS, plus OpenCV's where the CPU has AVX-512."""
    return {**PINS, **(dict([OPENCV_PIN]) if _has_avx512() else {})}


def mode() -> str:
    """The numeric mode this process runs in: ``RLSAC_NUMERICS``, else the record's (DEFAULT_MODE)."""
    return os.environ.get(ENV, "").strip() or DEFAULT_MODE


_LIBS = ("torch", "numpy", "cv2")  # the libraries that read their pin when they load
_APPLIED: dict = {"mode": None, "preloaded": []}  # what apply_pins found at `import rlsac`


def apply_pins() -> None:
    """In the portable mode, set every pin the user has not set (``import rlsac`` calls this first thing). An
    unknown mode sets nothing; ``check_mode`` reports it, and a library loaded before this call."""
    _APPLIED.update(mode=mode(), preloaded=[lib for lib in _LIBS if lib in sys.modules])
    set_pins(os.environ)


def set_pins(environ) -> None:
    """Set in ``environ`` (os.environ or a copy) every pin of its mode the user has not set."""
    if (environ.get(ENV, "").strip() or DEFAULT_MODE) == "portable":
        for k, v in pins().items():
            environ.setdefault(k, v)


def check_mode() -> str:
    """The mode, after checking it: RlsacError for an unknown one, or for a portable process whose pins did not
    take (a user value that contradicts one, or torch, numpy or OpenCV loaded before ``import rlsac`` set them)."""
    m = mode()
    if m not in MODES:
        raise RlsacError(f"{ENV}={m}: one of {', '.join(MODES)}")
    if m == "portable":
        off = [(k, v) for k, v in pins().items() if os.environ.get(k) != v]
        if off:
            k, v = off[0]
            raise RlsacError(f"{ENV}=portable needs {k}={v} (it is {os.environ.get(k)}); unset it or use "
                             f"{ENV}=native")
        # a library loaded before the pins keeps the code paths it chose (its bytes would be this CPU's)
        late = _APPLIED["preloaded"] if _APPLIED["mode"] == "portable" else [lib for lib in _LIBS if lib in sys.modules]
        if late:
            raise RlsacError(f"{ENV}=portable: {', '.join(late)} loaded before rlsac set the pins, and keeps the "
                             f"code paths it chose; import rlsac first, or set {ENV} before Python starts")
    return m


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
    for line in _cpuinfo().splitlines():
        if line.startswith("vendor_id"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown"


def describe() -> dict:
    """This machine's numeric platform: the KEYS plus what a reader wants beside them."""
    import cv2
    import numpy
    import torch

    branch = mkl_branch()
    return {"machine": platform.machine(), "numerics": mode(), "cpu_vendor": cpu_vendor(),
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
    if not isinstance(rec, dict):
        raise RlsacError(f"{path}: needs the string keys {', '.join(KEYS)}")
    rec = {"numerics": "native", **rec}  # records from before the modes were native
    if rec["numerics"] not in MODES or any(not isinstance(rec.get(k), str) for k in deciding_keys(rec)):
        raise RlsacError(f"{path}: needs the string keys {', '.join(deciding_keys(rec))} "
                         f"and numerics one of {', '.join(MODES)}")
    return rec


def deciding_keys(record: dict) -> tuple[str, ...]:
    """The fields that decide the bytes of a record made in its mode."""
    return PORTABLE_KEYS if record.get("numerics") == "portable" else ("numerics", *KEYS)


def differences(record: dict, here: dict) -> list[str]:
    """``key record -> here`` for every deciding key whose value differs (empty: the same platform)."""
    return [f"{k} {record[k]} -> {here[k]}" for k in deciding_keys(record) if record[k] != here[k]]


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
    lines = [f"{k:<16} record {c['record'][k]:<14} here {c['here'][k]}" for k in deciding_keys(c["record"])]
    diff = c["differences"]
    return lines + [f"platform: differs ({'; '.join(diff)})" if diff else "platform: the record's"]

