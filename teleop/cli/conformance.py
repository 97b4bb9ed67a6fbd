"""``teleop conformance operator|teleoperator``: check another implementation against PROTOCOL.md.

The suite (``conformance.checker``) plays the other side with this project's endpoint over UDP and
prints one line per rule (PASS/FAIL/SKIP, section, MUST/SHOULD); the exit status is 1 when a MUST
failed, 0 otherwise.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from teleop.cli.args import (
    CliError,
    Subcommands,
    add_key_args,
    add_robot_name_arg,
    add_transport_args,
    codec,
    float_range,
    udp_addr,
)
from teleop.cli.settings import endpoint_key, zenoh_options


def cmd_conformance(args: argparse.Namespace) -> int:
    from conformance.checker import check_operator, check_teleoperator, write_json

    psk, _ = endpoint_key(args)
    zenoh = None
    if args.transport == "zenoh":
        from teleop.session.fleet import default_prefix
        from transport.zenoh import TransportError, make_config

        z = zenoh_options(args)
        try:
            # No prefix: the one a teleoperator of this name takes by default (teleop.session.fleet)
            prefix = z.prefix or default_prefix(args.robot_name)
            zenoh = (prefix, make_config(z.mode, z.listen, z.connect, z.config_file))
        except (ValueError, TransportError) as e:
            raise CliError(str(e)) from None
    try:
        if args.role == "teleoperator":
            if args.peer is None and zenoh is None:
                raise CliError(
                    "--peer HOST:PORT is required with --transport udp (the teleoperator to check)"
                )
            result = check_teleoperator(
                args.peer, psk, args.robot_name, args.codec, args.duration, zenoh, not args.no_ghost_probe
            )
        else:
            listen = args.listen or ("127.0.0.1", 7000)
            result = check_operator(listen, psk, args.robot_name, args.timeout, zenoh)
    except OSError as e:  # the listen address is taken, the router cannot be reached
        raise CliError(str(e)) from None
    print(result.text())
    if args.json is not None:
        write_json(result, Path(args.json))
    return 1 if result.must_failed else 0


def add_parser(sub: Subcommands) -> None:
    c = sub.add_parser(
        "conformance",
        help="check another implementation's endpoint against PROTOCOL.md",
        description="Check an operator or a teleoperator written from PROTOCOL.md, section by section "
        "(the way h2spec checks HTTP/2): this command plays the other side over UDP or Zenoh with "
        "the project's own endpoint, adds probes (garbage, a wrong key, a cookie from another address, "
        "a malformed hello, a rejoin offer of the running session, a second operator), prints one line "
        "per rule and exits 1 when a MUST failed.",
    )
    c.add_argument(
        "role", choices=["operator", "teleoperator"], help="the role of the implementation to check"
    )
    c.add_argument(
        "--peer", type=udp_addr("--peer"), default=None, metavar="HOST:PORT", help="the teleoperator to check"
    )
    c.add_argument(
        "--listen",
        type=udp_addr("--listen"),
        default=None,
        metavar="HOST:PORT",
        help="where to wait for the operator to check (default 127.0.0.1:7000; point its --peer here)",
    )
    add_robot_name_arg(c, "--robot-name", "the robot name both sides' keys derive from")
    c.add_argument(
        "--codec",
        type=codec,
        default="none",
        metavar="SPEC",
        help="codec of the session proposed to a teleoperator (default none; any form --codec of "
        "teleop run takes)",
    )
    c.add_argument(
        "--duration",
        type=float_range("duration", 0.5, 60.0, "s"),
        default=1.5,
        help="with a teleoperator: seconds of data checked in each session the suite runs with it: the "
        "main one (proposed 5 s longer, left silent after this long so that the pd:5 session takes "
        "it over), and that pd:5 session (proposed and run this long). The ghost probe's session "
        "(4.3 step 8) is proposed 30 s long and ends within 2 s + R whatever this says (default 1.5)",
    )
    c.add_argument(
        "--timeout",
        type=float_range("timeout", 1.0, 3600.0, "s"),
        default=30.0,
        help="seconds to wait for the operator to say hello (default 30)",
    )
    c.add_argument(
        "--no-ghost-probe",
        action="store_true",
        help="with a teleoperator: skip the probe of section 4.3 step 8 (a session left silent from its "
        "start must end within 2 s + R, and another operator be served); it takes about 2 s",
    )
    c.add_argument("--json", metavar="FILE", default=None, help="also write the results as JSON to FILE")
    add_key_args(c, "required unless --insecure")
    add_transport_args(c)
    c.set_defaults(func=cmd_conformance)
