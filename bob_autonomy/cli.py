"""The `bob-autonomy` command: the on-vessel autonomy process.

Until the MAVLink vehicle interface lands, it lists the behaviours an agent can
run and their parameters, with units and defaults, so configurations can be
written against them.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

from behaviors.registry import BEHAVIORS


def _describe_behaviors() -> str:
    lines = []
    for name, cls in sorted(BEHAVIORS.items()):
        doc = (cls.__doc__ or "").strip().splitlines()[0]
        lines.append(f"{name}: {doc}")
        for f in dataclasses.fields(cls):
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
            lines.append(f"    {f.name} = {default!r}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bob-autonomy", description="BoB autonomy: the on-vessel agent process")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("behaviors", help="list the behaviours and their parameters")
    args = parser.parse_args(argv)
    if args.command == "behaviors":
        print(_describe_behaviors())
    return 0


if __name__ == "__main__":
    sys.exit(main())
