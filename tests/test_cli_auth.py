"""The key on the command line: `teleop keygen`, --key-file / --insecure, and `teleop run`'s own key.

In-process, with the session entry points replaced (no process is launched, no socket is opened
beyond `teleop run` picking a free port).
"""

from __future__ import annotations

import os
import signal
import stat
from pathlib import Path
from typing import Any

import pytest

import shell.process
import teleop.cli.run
from teleop.cli import CliError, build_parser, main
from teleop.cli.run import build_commands, run_key
from teleop.cli.settings import NO_KEY, session_params
from teleop.session import auth

PEER = ["operator", "--peer", "127.0.0.1:9", "--connect-timeout", "1"]
LISTEN = ["teleoperator", "--listen", "127.0.0.1:0", "--connect-timeout", "1"]


def _error(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run ``teleop ARGV`` in-process; assert exit status 2 and a one-line error; return it."""
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2, err
    assert err.startswith("teleop: error: ") and len(err.strip().splitlines()) == 1, err
    return err.strip()


def _key_file(tmp_path: Path, key: bytes | None = None, name: str = "teleop.key") -> Path:
    path = tmp_path / name
    auth.write_key_file(path, key if key is not None else auth.generate_key())
    return path


@pytest.fixture
def endpoints(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """The EndpointOptions each `teleop operator`/`teleoperator` would have run with."""
    got: list[Any] = []

    def run_endpoint(opts: Any, *args: Any) -> int:
        got.append(opts)
        return 0

    monkeypatch.setattr(shell.process, "run_endpoint", run_endpoint)
    return got


# --- teleop keygen ---------------------------------------------------------------------------------


def test_keygen_writes_a_private_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "teleop.key"
    assert main(["keygen", str(path)]) == 0
    key = auth.read_key_file(path)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    out = capsys.readouterr().out
    assert out == f"wrote key {auth.key_id(key)} to {path} (keep it secret; copy it to both hosts)\n"
    assert key.hex() not in out


def test_keygen_refuses_to_overwrite(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _key_file(tmp_path)
    before = path.read_bytes()
    err = _error(["keygen", str(path)], capsys)
    assert err == f"teleop: error: {path} exists; refusing to overwrite a key"
    assert path.read_bytes() == before
    err = _error(["keygen", str(tmp_path / "no-such-dir" / "k")], capsys)
    assert "cannot create key file" in err and "No such file or directory" in err
    assert "the following arguments are required: FILE" in _error(["keygen"], capsys)


# --- operator and teleoperator ---------------------------------------------------------------------


@pytest.mark.parametrize(
    "argv",
    [PEER, LISTEN, ["operator", "--transport", "zenoh"], ["teleoperator", "--transport", "zenoh"]],
    ids=["operator", "teleoperator", "operator-zenoh", "teleoperator-zenoh"],
)
def test_no_key_is_refused(argv: list[str], endpoints: list[Any], capsys: pytest.CaptureFixture[str]) -> None:
    err = _error(argv, capsys)
    assert err == f"teleop: error: {NO_KEY}"
    assert err == (
        "teleop: error: no key: pass --key-file FILE (make one with 'teleop keygen FILE') "
        "or --insecure to run unauthenticated"
    )
    assert endpoints == []


@pytest.mark.parametrize("argv", [PEER, LISTEN], ids=["operator", "teleoperator"])
def test_key_file_sets_the_psk(argv: list[str], endpoints: list[Any], tmp_path: Path) -> None:
    key = auth.generate_key()
    path = _key_file(tmp_path, key)
    assert main([*argv, "--key-file", str(path)]) == 0
    assert endpoints[0].psk == key and endpoints[0].insecure is False


@pytest.mark.parametrize("argv", [PEER, LISTEN], ids=["operator", "teleoperator"])
def test_insecure_sets_the_known_key(argv: list[str], endpoints: list[Any]) -> None:
    assert main([*argv, "--insecure"]) == 0
    assert endpoints[0].psk == auth.INSECURE_KEY and endpoints[0].insecure is True


@pytest.mark.parametrize("argv", [PEER, LISTEN, ["run"]], ids=["operator", "teleoperator", "run"])
def test_key_file_and_insecure_exclude_each_other(
    argv: list[str], endpoints: list[Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _key_file(tmp_path)
    err = _error([*argv, "--key-file", str(path), "--insecure"], capsys)
    assert "argument --insecure: not allowed with argument --key-file" in err
    assert endpoints == []


def _write(path: Path, text: str, mode: int) -> Path:
    path.write_text(text)
    path.chmod(mode)
    return path


BAD_KEY_FILES = [
    ("missing", lambda d: d / "nope.key", "does not exist (make one with 'teleop keygen "),
    ("directory", lambda d: d, "is a directory, not a key file"),
    ("not hex", lambda d: _write(d / "k", "not a key\n", 0o600), "does not hold a key"),
    ("short", lambda d: _write(d / "k", "ab" * 31 + "\n", 0o600), "expected 64 hex characters"),
    ("readable", lambda d: _write(d / "k", "ab" * 32 + "\n", 0o644), "(chmod 600 "),
    ("all zero", lambda d: _write(d / "k", "00" * 32 + "\n", 0o600), "all-zero key everyone knows"),
]


@pytest.mark.parametrize("argv", [PEER, LISTEN, ["run"]], ids=["operator", "teleoperator", "run"])
@pytest.mark.parametrize("make,msg", [b[1:] for b in BAD_KEY_FILES], ids=[b[0] for b in BAD_KEY_FILES])
def test_bad_key_file_is_one_clear_line(
    argv: list[str],
    make: Any,
    msg: str,
    endpoints: list[Any],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    def trip(cmd: list[str]) -> Any:
        raise AssertionError("a child started despite a bad key file")

    monkeypatch.setattr(teleop.cli.run, "_spawn", trip)
    keys = tmp_path / "keys"
    keys.mkdir()
    path = make(keys)
    out = ["--out", str(tmp_path / "out")] if argv == ["run"] else []
    err = _error([*argv, *out, "--key-file", str(path)], capsys)
    assert msg in err and str(path) in err
    assert endpoints == []


def test_helps_name_the_key_options(capsys: pytest.CaptureFixture[str]) -> None:
    for cmd in ("operator", "teleoperator", "run"):
        with pytest.raises(SystemExit):
            main([cmd, "--help"])
        out = " ".join(capsys.readouterr().out.split())
        assert "--key-file FILE" in out and "--insecure" in out and "teleop keygen FILE" in out, cmd
    with pytest.raises(SystemExit):
        main(["router", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "It takes no key" in out and "end to end" in out
    assert "--key-file" not in out.split("options:")[1] and "--insecure" not in out


def test_router_takes_no_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _key_file(tmp_path)
    err = _error(["router", "--listen", "tcp/127.0.0.1:1", "--key-file", str(path)], capsys)
    assert "unrecognized arguments: --key-file" in err


# --- teleop run ------------------------------------------------------------------------------------


def _run_args(tmp_path: Path, *extra: str) -> Any:
    return build_parser().parse_args(["run", "--out", str(tmp_path / "out"), *extra])


def _key_path(cmd: list[str]) -> Path:
    return Path(cmd[cmd.index("--key-file") + 1])


def _in_memory(path: Path) -> bool:
    """Whether ``path`` (``/proc/self/fd/N``) is the run's key in an anonymous memory file."""
    try:
        return os.readlink(path).startswith("/memfd:teleop-run-key")
    except OSError:
        return False


def test_run_makes_a_private_key_for_both_children_in_memory(tmp_path: Path) -> None:
    args = _run_args(tmp_path)
    params = session_params(args, 1234)
    with run_key(args) as key:
        cmds = build_commands(args, params, tmp_path, key)
        path = _key_path(cmds.teleoperator)
        assert _key_path(cmds.operator) == path and path.is_absolute()
        assert _in_memory(path) and key.pass_fds == (int(path.name),)  # never on disk
        assert stat.S_IMODE(path.stat().st_mode) == 0o600 and path.stat().st_uid == os.geteuid()
        assert key.source == "ephemeral" and key.key_id == auth.key_id(auth.read_key_file(path))
        with pytest.raises(PermissionError):  # sealed: nobody changes it under the children
            os.write(key.pass_fds[0], b"0")
        assert "--insecure" not in cmds.teleoperator + cmds.operator
        # what each child makes of its command line: the same key, authenticated
        for cmd, role in ((cmds.teleoperator, "teleoperator"), (cmds.operator, "operator")):
            assert cmd[3] == role
            child = build_parser().parse_args(cmd[3:])
            assert child.key_file == str(path) and child.insecure is False
    assert not _in_memory(path)


def test_each_run_has_its_own_key(tmp_path: Path) -> None:
    args = _run_args(tmp_path)
    with run_key(args) as a, run_key(args) as b:
        assert a.options != b.options
        assert auth.read_key_file(a.options[1]) != auth.read_key_file(b.options[1])


def test_run_with_a_key_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    key = auth.generate_key()
    _key_file(tmp_path, key, "given.key")
    monkeypatch.chdir(tmp_path)
    args = _run_args(tmp_path, "--key-file", "given.key")  # relative: the children get it absolute
    with run_key(args) as rk:
        cmds = build_commands(args, session_params(args, 7), tmp_path, rk)
    assert _key_path(cmds.operator) == _key_path(cmds.teleoperator) == tmp_path / "given.key"
    assert rk.source == "key-file" and rk.key_id == auth.key_id(key)
    assert (tmp_path / "given.key").exists()  # the user's key stays


def test_run_insecure(tmp_path: Path) -> None:
    args = _run_args(tmp_path, "--insecure")
    with run_key(args) as rk:
        cmds = build_commands(args, session_params(args, 7), tmp_path, rk)
    for cmd in (cmds.operator, cmds.teleoperator):
        assert "--insecure" in cmd and "--key-file" not in cmd
    assert (rk.source, rk.key_id) == ("insecure", "insecure")


def test_run_bad_key_file(tmp_path: Path) -> None:
    args = _run_args(tmp_path, "--key-file", str(tmp_path / "missing.key"))
    with pytest.raises(CliError, match="does not exist"), run_key(args):
        pass


def test_the_router_of_a_run_gets_no_key(tmp_path: Path) -> None:
    args = _run_args(tmp_path, "--transport", "zenoh", "--zenoh-mode", "client")
    with run_key(args) as rk:
        cmds = build_commands(args, session_params(args, 7), tmp_path, rk)
    assert cmds.net.router is not None and "router" in cmds.net.router
    assert "--key-file" not in cmds.net.router and "--insecure" not in cmds.net.router
    assert "--key-file" in cmds.operator and "--key-file" in cmds.teleoperator


class Boom(Exception):
    pass


@pytest.mark.parametrize("how", ["error", "ctrl-c", "sigterm"])
def test_run_removes_its_key_however_it_ends(
    how: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    if how == "sigterm" and signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        pytest.skip("SIGTERM is handled by the test runner")
    seen: list[Path] = []

    def spawn(cmd: list[str], pass_fds: tuple[int, ...] = ()) -> Any:
        path = _key_path(cmd)
        assert stat.S_IMODE(path.stat().st_mode) == 0o600  # there while the children start
        assert pass_fds == (int(path.name),) and _in_memory(path)
        seen.append(path)
        if how == "error":
            raise Boom
        if how == "ctrl-c":
            raise KeyboardInterrupt
        os.kill(os.getpid(), signal.SIGTERM)
        raise AssertionError("SIGTERM did not stop the run")

    monkeypatch.setattr(teleop.cli.run, "_spawn", spawn)
    argv = ["run", "--out", str(tmp_path / "out"), "--duration", "1"]
    if how == "error":
        with pytest.raises(Boom):
            main(argv)
    elif how == "ctrl-c":
        assert main(argv) == 130
    else:
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == 128 + signal.SIGTERM
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # the handler is put back
    assert len(seen) == 1 and not _in_memory(seen[0])
