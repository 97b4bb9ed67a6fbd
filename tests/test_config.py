"""Sessions from a file (issue 48): ``--config FILE`` (TOML, the flags' names), flags winning, and
``--print-config`` printing the settings in effect as a file that runs the same session again."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from teleop.cli.config import COMMANDS, MAX_CONFIG_BYTES
from teleop.cli.parser import build_parser, main

ARGS = {
    "run": ["--codec", "pdp:5", "--netem", "delay 10ms", "--link-timeout", "80", "--no-sim"],
    "sim": ["--codec", "ids:2", "--codec", "eds:50", "--duration", "2", "--b", "5"],
    "experiment": ["--runs", "2", "--codec", "eds:50", "--duration", "5", "--out", "exp"],
    "operator": ["--peer", "127.0.0.1:7000", "--codec", "cq:8", "--passivity", "tdpa", "--insecure"],
    "teleoperator": [
        "--listen",
        "127.0.0.1:7000",
        "--robot",
        "mujoco",
        "--max-velocity",
        "0.5",
        "--wait",
        "9",
    ],
}


def _printed(argv: list[str], capsys: Any) -> str:
    assert main([*argv, "--print-config"]) == 0
    return str(capsys.readouterr().out)


@pytest.mark.parametrize("command", COMMANDS)
def test_the_printed_settings_fed_back_are_the_same_settings(
    command: str, tmp_path: Path, capsys: Any
) -> None:
    text = _printed([command, *ARGS[command]], capsys)
    f = tmp_path / "session.toml"
    f.write_text(text)
    assert _printed([command, "--config", str(f)], capsys) == text
    direct = build_parser().parse_args([command, *ARGS[command]])
    from teleop.cli.config import expand
    from teleop.cli.parser import _commands

    via_file = build_parser().parse_args(expand([command, "--config", str(f)], _commands(build_parser())))
    same = {k: v for k, v in vars(direct).items() if k not in ("config", "func")}
    assert same == {k: v for k, v in vars(via_file).items() if k not in ("config", "func")}


def test_defaults_stay_comments_so_a_robot_fed_its_own_file_pins_nothing(tmp_path: Path, capsys: Any) -> None:
    text = _printed(["teleoperator", "--listen", "127.0.0.1:7000"], capsys)
    assert "\n# codec = (none)" in text and "\ncodec" not in text
    f = tmp_path / "robot.toml"
    f.write_text(text)
    from teleop.cli.config import expand
    from teleop.cli.parser import _commands

    args = build_parser().parse_args(expand(["teleoperator", "--config", str(f)], _commands(build_parser())))
    assert args.codec is None and args.scenario is None  # whatever the operator proposes


def test_a_flag_on_the_line_wins_over_the_file(tmp_path: Path, capsys: Any) -> None:
    f = tmp_path / "s.toml"
    f.write_text('codec = "pdp:5"\nduration = 3\nnetem = "delay 10ms"\nno-sim = true\n')
    text = _printed(["run", "--config", str(f), "--codec", "eds:50"], capsys)
    assert 'codec = "eds:50"' in text and 'codec = "pdp:5"' not in text
    assert 'duration = "3"' in text and "no-sim = true" in text


@pytest.mark.parametrize(
    ("content", "says"),
    [
        ('codex = "eds:50"\n', "unknown setting 'codex'; did you mean codec?"),
        ("duration = true\n", "duration must be a string or a number"),
        ('no-sim = "yes"\n', "no-sim is on or off: true or false"),
        ("x = [\n", "not TOML"),
        ('duration = "abc"\n', "duration must be a number, got 'abc'"),
        ('netem = "delay 50"\n', "a time needs its unit"),
    ],
)
def test_a_bad_file_is_one_line_naming_the_setting(
    content: str, says: str, tmp_path: Path, capsys: Any
) -> None:
    f = tmp_path / "bad.toml"
    f.write_text(content)
    with pytest.raises(SystemExit) as e:
        main(["run", "--config", str(f)])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert says in err and err.startswith("teleop: error: ")


def test_a_file_that_is_not_a_small_regular_one_is_refused(tmp_path: Path, capsys: Any) -> None:
    big = tmp_path / "big.toml"
    big.write_text("# " + "x" * MAX_CONFIG_BYTES + "\n")
    for path, says in ((big, "big.toml"), (Path("/dev/zero"), "not a regular file"), (tmp_path, "")):
        with pytest.raises(SystemExit):
            main(["sim", "--config", str(path)])
        err = capsys.readouterr().err
        assert err.startswith("teleop: error: --config") and says in err and err.count("\n") == 1


def test_the_guides_robot_file_is_read_as_written(tmp_path: Path, capsys: Any) -> None:
    guide = (Path(__file__).resolve().parents[1] / "docs" / "guides" / "first-session.md").read_text()
    block = guide.split("```toml\n", 1)[1].split("```", 1)[0]
    f = tmp_path / "robot.toml"
    f.write_text(block)
    text = _printed(["teleoperator", "--config", str(f)], capsys)
    assert 'robot = "franka:172.16.0.2:stiffness=1500,damping=80,force=spring"' in text
    assert 'max-velocity = "0.3"' in text and 'name = "arm-1"' in text
