"""``teleop keygen FILE``: a new pre-shared key, in a file only its owner can read."""

from __future__ import annotations

import argparse

from teleop.cli.args import CliError, Subcommands


def cmd_keygen(args: argparse.Namespace) -> int:
    from teleop.session import auth

    key = auth.generate_key()
    try:
        auth.write_key_file(args.file, key)
    except ValueError as e:
        raise CliError(str(e)) from None
    print(f"wrote key {auth.key_id(key)} to {args.file} (keep it secret; copy it to both hosts)")
    return 0


def add_parser(sub: Subcommands) -> None:
    k = sub.add_parser(
        "keygen",
        help="write a new pre-shared key for --key-file",
        description="Write a new random 256-bit pre-shared key to FILE (hex, mode 0600; an existing "
        "FILE is never overwritten). Copy it to both hosts over a secure channel (scp) and pass "
        "--key-file FILE to `teleop operator` and `teleop teleoperator`; the printed id names the "
        "key in their logs without revealing it. `teleop run` makes its own key for each run.",
    )
    k.add_argument("file", metavar="FILE", help="where to write the key (must not exist)")
    k.set_defaults(func=cmd_keygen)
