"""Wave variables stay bit-identical while TDPA is added beside them (issue 23).

The figures were printed by ``teleop sim``'s ``run_case`` before ``--passivity`` existed; any change
to the wave path (node, guard, codecs, wire) that moves one digit fails here.
"""

from __future__ import annotations

from teleop.sim import SimConfig, run_case

NET = "delay 20ms 5ms loss 5%"
GOLDEN = [
    (SimConfig(codec="eds:50"), (0.03410502322645739, 0.0, 2.2244952090525403, 0.0687562466344082, 0.0, 100)),
    (
        SimConfig(
            codec="pdp:1", scenario="protocol", duration=3.0, netem_forward=NET, netem_backward=NET, seed=3
        ),
        (0.18093126756632982, 0.0, 0.20538934909340048, 0.19865449683522865, 0.00176509444982821, 611),
    ),
    (
        SimConfig(codec="cq:8", scenario="protocol", duration=2.0, delay_ms=10),
        (0.013499321526784788, 0.0, 0.1318974722803938, 0.12639504352507916, 0.0, 2000),
    ),
]


def test_wave_figures_unchanged() -> None:
    for cfg, want in GOLDEN:
        s = run_case(cfg).summary
        got = (
            s["I"],
            s["min_energy_margin"],
            s["energy"]["forward"]["sent"],
            s["energy"]["backward"]["played"],
            s["passivity"]["forward"]["energy_dissipated"],
            s["wire"]["forward"]["packets"],
        )
        assert got == want, cfg
