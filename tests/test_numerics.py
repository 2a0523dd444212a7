"""The numeric modes (rlsac.numerics): the portable pins take in a fresh process, a mode that cannot take is a user
error, and a portable record is compared on the fields that decide its bytes."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from click.testing import CliRunner

from rlsac import numerics
from rlsac.cli import cli
from rlsac.errors import RlsacError
from tests.test_cli import assert_user_error

# what a fresh process sees after `import rlsac`: each library's own report of the code paths it took
PROBE = """
import json, os, rlsac, torch, numpy, cv2
from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
torch.ones(8, 8) @ torch.ones(8, 8)
print(json.dumps({"aten": torch.backends.cpu.get_cpu_capability(), "cv2": cv2.getCPUFeaturesLine(),
                  "ipp": cv2.ipp.getIppVersion() if cv2.ipp.useIPP() else "",
                  "numpy": [k for k in __cpu_dispatch__ if __cpu_features__.get(k)],
                  "env": {k: os.environ.get(k) for k in rlsac.numerics.pins()}}))
"""


def probe(mode: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in numerics.pins() and k != numerics.ENV}
    r = subprocess.run([sys.executable, "-c", PROBE], env={**env, numerics.ENV: mode}, capture_output=True,
                       text=True, check=True)
    return json.loads(r.stdout)


def test_a_library_loaded_before_rlsac_is_refused_in_the_portable_mode():
    code = "import numpy, rlsac; from rlsac import numerics; numerics.check_mode()"
    env = {k: v for k, v in os.environ.items() if k not in numerics.pins()}
    r = subprocess.run([sys.executable, "-c", code], env={**env, numerics.ENV: "portable"}, capture_output=True,
                       text=True)
    assert r.returncode == 1 and "RLSAC_NUMERICS=portable: numpy loaded before rlsac set the pins" in r.stderr
    ok = subprocess.run([sys.executable, "-c", code.replace("import numpy, rlsac", "import rlsac, numpy")],
                        env={**env, numerics.ENV: "portable"}, capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr


def test_portable_mode_pins_every_library_before_it_loads():
    p = probe("portable")
    assert p["env"] == numerics.pins()
    assert p["aten"] in ("AVX2", "DEFAULT")  # ATen runs AVX2 kernels even on an AVX-512 CPU
    assert not {"X86_V4", "AVX512_ICL", "AVX512_SPR"} & set(p["numpy"])
    assert "AVX512-SKX" not in p["cv2"].replace("AVX512-SKX?", "")  # '?': present but disabled
    # OpenCV's IPP has its own CPUID dispatcher (issue #63): its AVX2 kernels (l9), or none in a build without IPP
    assert p["ipp"] == "" or "(l9)" in p["ipp"], p["ipp"]
    n = probe("native")  # native sets nothing: each library takes this CPU's own paths
    assert n["env"] == {k: None for k in numerics.pins()}
    if numerics._has_avx512():
        assert n["aten"] == "AVX512" and "*AVX512-SKX?" not in n["cv2"] and "(l9)" not in n["ipp"]


def test_a_mode_that_cannot_take_is_a_user_error(monkeypatch):
    r = CliRunner().invoke(cli, ["verify", "--platform"], env={numerics.ENV: "fast"})
    assert_user_error(r, "RLSAC_NUMERICS=fast: one of native, portable")
    # a pin the user set otherwise would make the run neither portable nor native
    monkeypatch.setenv(numerics.ENV, "portable")
    for k, v in numerics.pins().items():
        monkeypatch.setenv(k, v)
    # a process started native that loaded torch and numpy then: the pins come too late to take
    monkeypatch.setitem(numerics._APPLIED, "mode", "native")
    with pytest.raises(RlsacError, match="torch, numpy.* loaded before rlsac set the pins"):
        numerics.check_mode()
    r = CliRunner().invoke(cli, ["verify", "--platform"], env={"MKL_CBWR": "AVX2"})
    assert_user_error(r, "RLSAC_NUMERICS=portable needs MKL_CBWR=COMPATIBLE (it is AVX2)")


def test_a_portable_record_is_decided_by_the_mode_and_atens_level(tmp_path):
    here = {"machine": "x86_64", "numerics": "portable", "cpu_vendor": "AuthenticAMD", "mkl_branch": "generic",
            "aten_capability": "AVX2"}
    rec = {**here, "cpu_vendor": "GenuineIntel", "mkl_branch": "AVX-512"}
    (tmp_path / "reports").mkdir()
    (tmp_path / numerics.RECORD).write_text(json.dumps(rec))
    loaded = numerics.load_record(tmp_path)
    assert numerics.differences(loaded, here) == []  # the vendor and MKL's branch no longer decide
    assert numerics.differences(loaded, {**here, "numerics": "native", "aten_capability": "AVX512"}) == [
        "numerics portable -> native", "aten_capability AVX2 -> AVX512"]
    # a record from before the modes was native, and there the vendor decides
    native = {k: v for k, v in rec.items() if k != "numerics"}
    (tmp_path / numerics.RECORD).write_text(json.dumps(native))
    assert numerics.differences(numerics.load_record(tmp_path), {**here, "numerics": "native"}) == [
        "cpu_vendor GenuineIntel -> AuthenticAMD", "mkl_branch AVX-512 -> generic"]
