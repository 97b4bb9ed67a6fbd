"""``teleop sim`` stays bit-identical while the 1 kHz loop is made cheap (issue 22).

Recorded before any hot-path change: each case's transparency figure ``I`` to the last digit and a
SHA-256 over every trace array (signals, energy margins, per-tick payload and packet bytes) and the
whole summary, on OpenBLAS's SkylakeX kernels; ``ON_HASWELL`` holds the cases whose bits differ on
its Haswell kernels (``tests/blas.py``: the same code, recorded on an AMD EPYC host that sets them,
after checking that it gives every SkylakeX figure with SkylakeX's kernels).  A faster encoder that
changes one wire byte, or an in-place update that reorders one floating-point sum, fails here.
The hashes were recorded again once (issue 34) when the summary's counters gained
``device_stale`` and ``saturated``: every ``I`` and every trace array stayed bit-identical (checked
with the trace-only digest on both kernels before and after), only those two keys were added.
Covers codecs beyond ``tests/test_wave_golden.py``: ``none`` at 2 and 6 DoF, ``eds:50`` with delay,
``pdp:1`` and ``cq:8`` over lossy jittery links, and TDPA.
"""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from teleop.offline.sim import CaseResult, SimConfig, run_case
from tests.blas import golden_kernel

NET = "delay 20ms 5ms loss 5%"
P = {"scenario": "protocol", "duration": 2.0}
GOLDEN: dict[str, tuple[SimConfig, float, str]] = {
    "none-step": (
        SimConfig(codec="none"),
        0.0004995202139319017,
        "697194f5dcf9b08c16000ced419fd4c9a51b6cb638353ff49bc7ea19056e20b0",
    ),
    "none-6dof": (
        SimConfig(codec="none", dof=6, **P),  # type: ignore[arg-type]
        4.2454925259061775e-05,
        "e1356307ac96d42b5debece4f9c4e0d8f679b9abc61a9e83992b2dc01db300f0",
    ),
    "eds-delay": (
        SimConfig(codec="eds:50", delay_ms=10, **P),  # type: ignore[arg-type]
        0.15249833045860367,
        "645f68aecb91731d3d3292b340e6c3387c42f5e9b89ac5f5d4891506941961fe",
    ),
    "pdp-netem": (
        SimConfig(codec="pdp:1", netem_forward=NET, netem_backward=NET, seed=5, **P),  # type: ignore[arg-type]
        0.09663898368785266,
        "3cb35c73ec32e54bf56570066a97933f1d58f27a0afe3b66e71350bed862d265",
    ),
    "cq8-netem": (
        SimConfig(codec="cq:8", netem_forward=NET, netem_backward=NET, seed=7, **P),  # type: ignore[arg-type]
        0.07171201470244709,
        "4f9b5caa0f9c8b166614605267c88f9665898e35f17215a8b11ba9b0f4494d49",
    ),
    "tdpa-pdp": (
        SimConfig(codec="pdp:1", delay_ms=20, passivity="tdpa", **P),  # type: ignore[arg-type]
        0.02544233898123922,
        "db4b17f368125fa12e03db15698532fdb7ee0cd68c86dc0ad39cf36e8d70ff29",
    ),
    # The whole Section VI task (free space, foam, wall), a varied plan at 3 DoF: the human's push
    # profile and the environment's contact branches, which the 2 s cases never reach.  Recorded
    # from 1101014, before this case's hot-path changes.
    "pdp-protocol-15s-varied": (
        SimConfig(codec="pdp:1", dof=3, scenario="protocol", duration=15.0, variation=1.0, seed=3),
        0.001160279259017192,
        "dd63659e1fce715d1bb948053e88b9a3bf1241d0e16c5440b76b30ede398448e",
    ),
    "tdpa-none-netem": (
        SimConfig(codec="none", netem_forward=NET, netem_backward=NET, seed=2, passivity="tdpa", **P),  # type: ignore[arg-type]
        0.025495322116358087,
        "4a8fe80a2c6adb5db4d4797db326cbc38b8b7a8ab602814553d3e33a21d80eab",
    ),
}


# The same code's figures on OpenBLAS's Haswell kernels, where they differ (recorded at ae61552 on an
# AMD EPYC host with OPENBLAS_CORETYPE=Haswell; with SkylakeX's kernels it gave every figure above).
ON_HASWELL: dict[str, tuple[float, str]] = {
    "none-6dof": (
        4.2454925259061775e-05,
        "885f76646afdd2c4c68e91b16c0dba7eade6736b551c2593ec7882880f6c216c",
    ),
    "pdp-netem": (
        0.09663937842999064,
        "d8e660114d03de335c429ea6a050e0013f54d7474dd6e62ee52dc0646d169cad",
    ),
    "cq8-netem": (
        0.07171201470244817,
        "d8b1b769009f2e9c949e661452deb6d9c5ebdd40eab991130918a5a5ca8610af",
    ),
    "pdp-protocol-15s-varied": (
        0.001169762527841878,
        "178558bef71ca71c29b4f725793f61eaec84d8f09372cc48dd44545517551199",
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
