"""``teleop robots``: the robots announced through a Zenoh router, with their state.

A robot is listed *trusted* when it is alive (its liveliness token) and its description verifies
under its key, derived from the deployment key (``--key-file``) and its name; anything else alive
under ``teleop/robots`` is listed as untrusted, with why.  The listing shows claims, never makes them:
the session handshake is the only claim (``teleop operator --robot-name NAME``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

from teleop.cli.args import CliError, Subcommands, add_key_args, positive_float, robot_name, zenoh_config_file
from teleop.cli.settings import endpoint_key
from teleop.errors import one_line


def _row(r: Any) -> dict[str, Any]:
    d = r.description
    if d is None:
        return {"name": r.name, "trusted": False, "problem": r.problem}
    return {
        "name": d.name,
        "trusted": True,
        "state": d.state,
        "holder": d.holder,
        "dof": d.dof,
        "kind": d.kind,
        "prefix": d.prefix,
        "envelope": d.envelope,
    }


def cmd_robots(args: argparse.Namespace) -> int:
    from transport.fleet import list_robots
    from transport.zenoh import TransportError, make_config, open_session

    psk, _ = endpoint_key(args)
    connect = list(args.zenoh_connect or []) + ([args.zenoh_router] if args.zenoh_router else [])
    try:
        config = make_config("client", None, connect or None, args.zenoh_config)
        session = open_session(config)
    except (TransportError, ValueError) as e:
        raise CliError(str(e)) from None
    try:
        t0 = time.monotonic()
        robots = list_robots(session, psk, args.name, timeout=args.timeout)
        took = time.monotonic() - t0
    except TransportError as e:
        raise CliError(str(e)) from None
    finally:
        session.close()
    rows = [_row(r) for r in robots]
    if args.json:
        json.dump({"robots": rows, "seconds": round(took, 4)}, sys.stdout, indent=1)
        print()
        return 0
    print("\n".join(table(rows, took)))
    return 0


def table(rows: list[dict[str, Any]], took: float) -> list[str]:
    """The listing's lines.  Every field a robot sent (its name, a problem's text quoting it, its
    kind and prefix) is shown escaped with ``one_line``: a robot on the router, trusted or not,
    must not forge a line or drive the terminal with an escape sequence."""
    trusted = sum(r["trusted"] for r in rows)
    lines = [
        f"{len(rows)} robots ({trusted} trusted) in {took * 1e3:.0f} ms",
        f"  {'NAME':<20} {'STATE':<6} {'HELD BY':<12} {'DOF':>3}  {'KIND':<8} PREFIX",
    ]
    for r in rows:
        name = one_line(r["name"])
        if not r["trusted"]:
            lines.append(f"  {name:<20} UNTRUSTED: {one_line(r['problem'])}")
            continue
        holder = (
            f"{r['holder']:#010x}"
            if r["holder"] is not None
            else ("-" if r["state"] == "free" else "(hidden)")
        )
        state, kind, prefix = (one_line(r[k]) for k in ("state", "kind", "prefix"))
        lines.append(f"  {name:<20} {state:<6} {holder:<12} {r['dof']:>3}  {kind:<8} {prefix}")
    return lines


def add_parser(sub: Subcommands) -> None:
    r = sub.add_parser(
        "robots",
        help="list the robots announced through a Zenoh router",
        description="List the robots announced through a Zenoh router: name, free or busy (and by "
        "which session, if the robot shows it), DoF, device kind, data keys. A robot whose "
        "description does not verify under the deployment key is listed as UNTRUSTED.",
    )
    r.add_argument("--zenoh-router", metavar="ENDPOINT", help="the router, e.g. tcp/10.0.0.5:7447")
    r.add_argument(
        "--zenoh-connect",
        action="append",
        metavar="ENDPOINT",
        help="another endpoint to connect to (repeatable)",
    )
    r.add_argument(
        "--zenoh-config",
        metavar="FILE",
        type=zenoh_config_file,
        help="Zenoh JSON5 config loaded first (deploy/zenoh/*.json5: TLS, user and password)",
    )
    r.add_argument("--name", type=robot_name("--name"), default=None, help="only the robot of this name")
    r.add_argument(
        "--timeout",
        type=positive_float("timeout", 30.0, "s"),
        default=1.0,
        metavar="S",
        help="how long to wait for the robots' answers (default 1 s)",
    )
    r.add_argument("--json", action="store_true", help="print the listing as JSON")
    add_key_args(r, "required unless --insecure: it verifies each robot's description")
    r.set_defaults(func=cmd_robots)
