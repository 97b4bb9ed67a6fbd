"""``teleop sim`` stays bit-identical while the 1 kHz loop is made cheap (issue 22).

Recorded before any hot-path change: each case's transparency figure ``I`` to the last digit and a
SHA-256 over every trace array (signals, energy margins, per-tick payload and packet bytes) and the
whole summary, on OpenBLAS's SkylakeX kernels; ``ON_HASWELL`` holds the cases whose bits differ on
its Haswell kernels (``tests/blas.py``: the same code, recorded on an AMD EPYC host that sets them,
after checking that it gives every SkylakeX figure with SkylakeX's kernels).  A faster encoder that
changes one wire byte, or an in-place update that reorders one floating-point sum, fails here.
Covers codecs beyond ``tests/test_wave_golden.py``: ``none`` at 2 and 6 DoF, ``eds:50`` with delay,
``pdp:1`` and ``cq:8`` over lossy jittery links, and TDPA.
"""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from teleop.sim import CaseResult, SimConfig, run_case
from tests.blas import golden_kernel

NET = "delay 20ms 5ms loss 5%"
P = {"scenario": "protocol", "duration": 2.0}
GOLDEN: dict[str, tuple[SimConfig, float, str]] = {
    "none-step": (
        SimConfig(codec="none"),
        0.0004995202139319017,
        "b2dc3aebfd76b4869f843853e9fd7c50dff9884db69a052316b6f2a22160eb4a",
    ),
    "none-6dof": (
        SimConfig(codec="none", dof=6, **P),  # type: ignore[arg-type]
        4.2454925259061775e-05,
        "7485439e2ab933b77008fae209845982ec0d0192a09435b1e3549f6d3a018af5",
    ),
    "eds-delay": (
        SimConfig(codec="eds:50", delay_ms=10, **P),  # type: ignore[arg-type]
        0.15249833045860367,
        "590aa8a4dcf87ecf2611cbdc40f43e85ec4e5df126e90b8becb3c6fbba29014e",
    ),
    "pdp-netem": (
        SimConfig(codec="pdp:1", netem_forward=NET, netem_backward=NET, seed=5, **P),  # type: ignore[arg-type]
        0.09663898368785266,
        "20522e8ba869659fe211645dec6fd69b0aaa478321cad2ec6776242cbc01ffde",
    ),
    "cq8-netem": (
        SimConfig(codec="cq:8", netem_forward=NET, netem_backward=NET, seed=7, **P),  # type: ignore[arg-type]
        0.07171201470244709,
        "262cbbbcfba556e303eefc70320ede3cf76f786ba9a065816cf08e4cd13a230c",
    ),
    "tdpa-pdp": (
        SimConfig(codec="pdp:1", delay_ms=20, passivity="tdpa", **P),  # type: ignore[arg-type]
        0.02544233898123922,
        "563b06371d4851355c1b3661dd2728d6c5aa637f08ea808d06b4e012d90ddac0",
    ),
    # The whole Section VI task (free space, foam, wall), a varied plan at 3 DoF: the human's push
    # profile and the environment's contact branches, which the 2 s cases never reach.  Recorded
    # from 1101014, before this case's hot-path changes.
    "pdp-protocol-15s-varied": (
        SimConfig(codec="pdp:1", dof=3, scenario="protocol", duration=15.0, variation=1.0, seed=3),
        0.001160279259017192,
        "203215cbbb9bec763883b06004a70a1969011278f5cfa4ecda7378da8e6b073d",
    ),
    "tdpa-none-netem": (
        SimConfig(codec="none", netem_forward=NET, netem_backward=NET, seed=2, passivity="tdpa", **P),  # type: ignore[arg-type]
        0.025495322116358087,
        "49e6011a49c2d27d99b6f73d7857b587fad4748404c0f3565df3a3f7705b2c7d",
    ),
}


# The same code's figures on OpenBLAS's Haswell kernels, where they differ (recorded at ae61552 on an
# AMD EPYC host with OPENBLAS_CORETYPE=Haswell; with SkylakeX's kernels it gave every figure above).
ON_HASWELL: dict[str, tuple[float, str]] = {
    "none-6dof": (
        4.2454925259061775e-05,
        "2244a619ecdb33b06b0e0f9586df3890ad1d292c4b927cdb729cb6c334911bae",
    ),
    "pdp-netem": (
        0.09663937842999064,
        "73ee0e466a261a10617755d9c5d67799e679401836b3e3079f6ee9363757ad05",
    ),
    "cq8-netem": (
        0.07171201470244817,
        "abada2c74f54bd9382d2dad132a1c3631a5cff1dfee1368ba25dc9534e2683c6",
    ),
    "pdp-protocol-15s-varied": (
        0.001169762527841878,
        "57df94e03ac0c4e7fe92418405c9c3eb009766d83489e02840d4da4b0a57f0a9",
    ),
}


def digest(r: CaseResult) -> str:
    h = hashlib.sha256()
    tr = r.trace
    for a in (tr.t, tr.v_hsi, tr.f_hsi, tr.v_to, tr.f_to, tr.margin_fwd, tr.margin_bwd):
        h.update(np.ascontiguousarray(a).tobytes())
    for d in sorted(tr.payload_bytes):
        h.update(np.ascontiguousarray(tr.payload_bytes[d]).tobytes())
    for d in sorted(tr.packet_bytes):
        h.update(np.ascontiguousarray(tr.packet_bytes[d]).tobytes())
    h.update(json.dumps(r.summary, sort_keys=True, default=str).encode())
    return h.hexdigest()


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_sim_bit_identical(name: str) -> None:
    cfg, i_want, sha_want = GOLDEN[name]
    if golden_kernel() == "Haswell":
        i_want, sha_want = ON_HASWELL.get(name, (i_want, sha_want))
    r = run_case(cfg)
    assert r.summary["I"] == i_want
    assert digest(r) == sha_want
