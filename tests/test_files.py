"""Files as input and output (issue 21, item 3): a trace or a Zenoh config is a regular file of
bounded size, refused by its type before it is opened (a FIFO or a device never hangs or fills
memory); a log folder another user can write is refused.  Each case is one ``teleop: error:`` line.
"""

from __future__ import annotations

import json
import os
import signal
from collections.abc import Iterator
from pathlib import Path

import pytest

from teleop import files
from teleop.cli import main
from teleop.session.link.netem import NetemError, load_trace
from transport.zenoh import make_config

PEER = ["--peer", "127.0.0.1:9", "--connect-timeout", "1"]
ZENOH = ["--transport", "zenoh", "--zenoh-listen", "tcp/127.0.0.1:0"]


@pytest.fixture(autouse=True)
def no_hang() -> Iterator[None]:
    """A read that blocks (a FIFO opened without O_NONBLOCK) fails the test instead of hanging it."""

    def hung(signum: int, frame: object) -> None:
        raise TimeoutError("hung on a file")

    old = signal.signal(signal.SIGALRM, hung)
    signal.alarm(20)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


@pytest.fixture
def fifo(tmp_path: Path) -> Path:
    p = tmp_path / "fifo"
    os.mkfifo(p)
    return p


def _inputs(tmp_path: Path, fifo: Path) -> dict[str, tuple[Path, str]]:
    big = tmp_path / "big"
    with big.open("wb") as f:
        f.truncate(files.MAX_TRACE_BYTES + 1)  # sparse: costs no disk
    return {
        "fifo": (fifo, "a FIFO, not a regular file"),
        "dev_zero": (Path("/dev/zero"), "a character device, not a regular file"),
        "dev_urandom": (Path("/dev/urandom"), "a character device, not a regular file"),
        "directory": (tmp_path, "a directory, not a regular file"),
        "too_big": (big, f"more than the {files.MAX_TRACE_BYTES} accepted"),
    }


KINDS = ["fifo", "dev_zero", "dev_urandom", "directory", "too_big"]


def _one_line(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2, err
    assert "Traceback" not in err
    assert err.startswith("teleop: error: ") and len(err.strip().splitlines()) == 1, err
    return err


@pytest.mark.parametrize("kind", KINDS)
def test_trace_loader_refuses_by_type_and_size(kind: str, tmp_path: Path, fifo: Path) -> None:
    path, why = _inputs(tmp_path, fifo)[kind]
    with pytest.raises(NetemError, match=why):
        load_trace(path)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize(
    "cmd", [["sim"], ["run"], ["operator", *PEER], ["teleoperator", "--listen", "127.0.0.1:0"]]
)
def test_every_command_refuses_a_bad_trace(
    cmd: list[str], kind: str, tmp_path: Path, fifo: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, why = _inputs(tmp_path, fifo)[kind]
    opt = "--netem-forward" if cmd[0] == "teleoperator" else "--netem"
    assert why in _one_line([*cmd, opt, f"trace {path}"], capsys)


@pytest.mark.parametrize("kind", ["fifo", "dev_zero", "directory"])
def test_zenoh_config_refuses_by_type(
    kind: str, tmp_path: Path, fifo: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, why = _inputs(tmp_path, fifo)[kind]
    with pytest.raises(ValueError, match=why):
        make_config("peer", ["tcp/127.0.0.1:0"], None, str(path))
    assert why in _one_line(["operator", *ZENOH, "--zenoh-config", str(path)], capsys)
    assert why in _one_line(["router", "--config", str(path)], capsys)


def test_zenoh_config_size_is_bounded(tmp_path: Path) -> None:
    big = tmp_path / "big.json5"
    with big.open("wb") as f:
        f.truncate(files.MAX_CONFIG_BYTES + 1)
    with pytest.raises(ValueError, match=f"more than the {files.MAX_CONFIG_BYTES} accepted"):
        make_config("peer", ["tcp/127.0.0.1:0"], None, str(big))


def test_a_good_trace_and_config_still_load(tmp_path: Path) -> None:
    trace = tmp_path / "trace"
    trace.write_text("1\n2\n")
    assert load_trace(trace) == [1.0, 2.0]
    link = tmp_path / "link"
    link.symlink_to(trace)  # a symlink the user names is followed once, by resolving it
    assert load_trace(link) == [1.0, 2.0]
    cfg = tmp_path / "z.json5"
    cfg.write_text('{ "mode": "peer" }')
    make_config("peer", ["tcp/127.0.0.1:0"], None, str(cfg))


@pytest.mark.parametrize("mode", [0o777, 0o775, 0o757])
def test_a_log_folder_others_can_write_is_refused(tmp_path: Path, mode: int) -> None:
    d = tmp_path / "logs"
    d.mkdir()
    d.chmod(mode)
    with pytest.raises(files.FileRefused, match="writable by other users"):
        files.check_private_dir(d)
    d.chmod(mode | 0o1000)  # sticky, as /tmp: names cannot be taken from us; O_EXCL does the rest
    files.check_private_dir(d)
    d.chmod(0o755)
    files.check_private_dir(d)


@pytest.mark.skipif(os.geteuid() != 0, reason="giving a folder to another user (chown) needs root")
def test_a_log_folder_of_another_user_is_refused(tmp_path: Path) -> None:
    d = tmp_path / "logs"
    d.mkdir()
    os.chown(d, os.geteuid() + 1, -1)
    with pytest.raises(files.FileRefused, match="owned by uid"):
        files.check_private_dir(d)


def test_create_new_never_follows_or_overwrites(tmp_path: Path) -> None:
    victim = tmp_path / "victim"
    victim.write_text("precious")
    (tmp_path / "planted").symlink_to(victim)
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    for name in ("victim", "planted", "dangling"):
        with pytest.raises(OSError) as e:
            files.create_new(tmp_path / name)
        assert files.is_exists(e.value)
    assert victim.read_text() == "precious" and not (tmp_path / "nowhere").exists()


@pytest.mark.parametrize("cmd", [["operator", *PEER], ["teleoperator", "--listen", "127.0.0.1:0"]])
def test_the_commands_refuse_a_log_folder_others_can_write(
    cmd: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    logs = tmp_path / "logs"
    logs.mkdir()
    logs.chmod(0o777)
    err = _one_line([*cmd, "--insecure", "--log", str(logs)], capsys)
    assert f"--log {logs}: writable by other users (mode 777)" in err


@pytest.mark.parametrize(
    ("cmd", "name"),
    [
        (["sim", "--duration", "0.2", "--codec", "none"], "results.json"),
        (["sweep", "--duration", "0.2", "--codec", "none"], "sweep.json"),
        (["experiment", "--duration", "0.2", "--codec", "none", "--runs", "1"], "experiment.json"),
    ],
)
def test_an_output_is_never_overwritten_nor_written_through_a_symlink(
    cmd: list[str], name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    victim = tmp_path / "victim"
    victim.write_text("precious")
    out = tmp_path / "out"
    out.mkdir()
    (out / name).symlink_to(victim)
    err = _one_line([*cmd, "--out", str(out)], capsys)
    assert f"already holds {name}: outputs are never overwritten" in err
    assert victim.read_text() == "precious"


def test_a_plot_is_never_written_through_a_symlink(tmp_path: Path) -> None:
    import numpy as np

    from teleop.offline import plots

    victim = tmp_path / "victim"
    victim.write_text("precious")
    (tmp_path / "signals.png").symlink_to(victim)
    t = np.zeros(2)
    v = np.zeros((2, 1))
    with pytest.raises(files.FileRefused, match="outputs are never overwritten"):
        plots.velocity_force(tmp_path / "signals.png", t, v, v, v, v, "x")
    assert victim.read_text() == "precious"


def test_a_log_folder_the_stack_makes_is_private_whatever_the_umask(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Under umask 002 a plain mkdir makes a group-writable folder, which would then be refused."""
    import shell.process

    class Started(Exception):
        pass

    def trip(*args: object, **kwargs: object) -> int:
        raise Started

    monkeypatch.setattr(shell.process, "run_endpoint", trip)
    logs = tmp_path / "new" / "logs"
    old = os.umask(0o002)
    try:
        with pytest.raises(Started):
            main(["operator", *PEER, "--insecure", "--log", str(logs)])
    finally:
        os.umask(old)
    assert os.stat(logs).st_mode & 0o777 == 0o755


@pytest.mark.parametrize(
    "key", ["transport/auth/usrpwd/dictionary_file", "transport/link/tls/root_ca_certificate"]
)
@pytest.mark.parametrize("kind", ["fifo", "dev_zero", "directory"])
def test_a_file_the_zenoh_config_names_is_refused_by_type(
    key: str, kind: str, tmp_path: Path, fifo: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Zenoh opens these itself, before anything of ours runs: a FIFO named as the usrpwd
    dictionary hung zenoh.open past SIGTERM; now make_config refuses it in one line."""
    path, why = _inputs(tmp_path, fifo)[kind]
    *parents, leaf = key.split("/")
    nested: dict[str, object] = {leaf: str(path)}
    for p in reversed(parents):
        nested = {p: nested}
    cfg = tmp_path / "named.json5"
    cfg.write_text(json.dumps(nested))
    with pytest.raises(ValueError, match=why):
        make_config("peer", ["tcp/127.0.0.1:0"], None, str(cfg))
    # The file is read when the session opens: the endpoint's one line, exit 1.
    assert main(["operator", "--insecure", *ZENOH, "--zenoh-config", str(cfg)]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert err.startswith("teleop operator: error: ") and key in err and why in err, err
