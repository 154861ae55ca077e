"""The `faceplan` command line.

Each sub-command is a small function in its own module, registered here. Exit status follows
the contract: 0 done, 2 bad input (`planner.errors.InputError`), 3 the model could not be solved
(`planner.errors.SolveError`), 4 the machine refused (disk full, read-only or failing file
system, permission denied while writing: `planner.atomic.is_environment_error`; nothing
half-written is left), 130 interrupted (Ctrl-C, or SIGTERM: 143). User mistakes and faults of
the machine never show a traceback.
"""
from __future__ import annotations

import argparse
import signal
import sys

EXIT_ENVIRONMENT = 4
EXIT_INTERRUPTED = 130

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


class Terminated(BaseException):
    """SIGTERM, raised in the main thread so that `with` blocks clean up as for Ctrl-C."""


def _on_sigterm(signum, frame):
    raise Terminated()


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
        epilog="exit status: 0 done, 2 bad input, 3 the model could not be solved, 4 disk full / "
               "not writable, 130 interrupted",
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


def _run(argv: list[str] | None) -> int:
    from planner.atomic import is_environment_error
    from planner.errors import InputError, SolveError

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
    except OSError as exc:
        if not is_environment_error(exc):
            raise
        where = f" ({exc.filename})" if exc.filename else ""
        print(f"faceplan {args.command}: error: {exc.strerror or exc}{where}; nothing was written",
              file=sys.stderr)
        return EXIT_ENVIRONMENT


def main(argv: list[str] | None = None) -> int:
    """Run one command; every exit path, including Ctrl-C during start-up, returns a status."""
    try:
        if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
            signal.signal(signal.SIGTERM, _on_sigterm)
    except ValueError:        # not the main thread: leave signals alone
        pass
    try:
        return _run(argv)
    except KeyboardInterrupt:
        print("faceplan: interrupted; nothing was written", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Terminated:
        print("faceplan: terminated; nothing was written", file=sys.stderr)
        return 128 + signal.SIGTERM


if __name__ == "__main__":
    sys.exit(main())
