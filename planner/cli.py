"""The `faceplan` command line.

Each sub-command is a small function in its own module, registered here. Exit status follows
the contract: 0 done, 2 bad input (`planner.errors.InputError`), 3 the model could not be solved
(`planner.errors.SolveError`). User mistakes never show a traceback.
"""
from __future__ import annotations

import argparse
import sys

from planner.errors import InputError, SolveError

# name -> (module path, one-line help). Modules expose `add_arguments(parser)` and `run(args)`.
COMMANDS = {
    "demo": ("planner.commands.demo", "the whole prediction on an embedded synthetic head and sample plan"),
    "register": ("planner.commands.register", "generic mesh -> patient mesh (Mesh-Match-and-Repair)"),
    "predict": ("planner.commands.predict", "plan -> predicted face"),
    "compare": ("planner.commands.compare", "prediction vs post-operative scan"),
    "diagnose": ("planner.commands.diagnose", "sim-to-real gap diagnosis"),
    "synth": ("planner.commands.synth", "synthetic case folders"),
    "calibrate": ("planner.commands.calibrate", "material parameters from aspiration / indentation data"),
}


def _load(name: str):
    import importlib

    modname = COMMANDS[name][0]
    try:
        return importlib.import_module(modname)
    except ModuleNotFoundError as exc:
        if exc.name == modname:
            return None
        raise


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="faceplan",
        description="Predict the face after orthognathic surgery and diagnose where predictions miss.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, help_text) in COMMANDS.items():
        mod = _load(name)
        p = sub.add_parser(name, help=help_text if mod else help_text + " (not available in this build)",
                           description=help_text)
        if mod is not None:
            mod.add_arguments(p)
        else:
            p.add_argument("rest", nargs=argparse.REMAINDER)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    mod = _load(args.command)
    if mod is None:
        print(f"faceplan {args.command}: not available in this build", file=sys.stderr)
        return 2
    try:
        return int(mod.run(args) or 0)
    except InputError as exc:
        print(f"faceplan {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except SolveError as exc:
        print(f"faceplan {args.command}: the model could not be solved: {exc}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


def entry(argv: list[str] | None = None) -> int:
    """The `faceplan` command: `main`, with any other exception (not bad input, not a solve
    failure: a bug) shown as one: its traceback, a line asking to report it, exit status 1."""
    try:
        return main(argv)
    except Exception:
        import traceback

        traceback.print_exc()
        print("faceplan: this is a bug in faceplan: please report it with the command line",
              file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(entry())
