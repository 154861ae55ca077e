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
import threading

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


class _Interrupts:
    """SIGINT / SIGTERM handling that a library cannot swallow.

    The first signal raises KeyboardInterrupt (Terminated for SIGTERM) in the main thread, as
    Python does. Some libraries catch BaseException around their optional imports (an
    interrupt during start-up then vanishes, or resurfaces later as an unrelated NameError), so
    until `main` has returned, the signal is delivered again every `REPEAT_S` seconds, and any
    exception after an interrupt counts as the interrupt."""

    REPEAT_S = 0.5

    def __init__(self):
        self.pending: int | None = None
        self.done = threading.Event()
        self.saved = {}

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        for sig in (signal.SIGINT, signal.SIGTERM):
            current = signal.getsignal(sig)
            if current in (signal.SIG_DFL, signal.default_int_handler):
                self.saved[sig] = current
                signal.signal(sig, self._handler)
        self._hook = sys.unraisablehook
        sys.unraisablehook = self._unraisable

    def restore(self) -> None:
        self.done.set()
        for sig, handler in self.saved.items():
            signal.signal(sig, handler)
        if getattr(self, "_hook", None) is not None:
            sys.unraisablehook = self._hook
            self._hook = None

    def _unraisable(self, info) -> None:
        """An interrupt raised while Python runs a finalizer (`__del__`, a weakref callback) is
        not propagated: Python prints it as "Exception ignored" with a traceback. That is our
        own signal, which the repeat delivers again, so it is not reported; anything else is."""
        if self.pending is not None and isinstance(info.exc_value, (KeyboardInterrupt, Terminated)):
            return
        (self._hook or sys.__unraisablehook__)(info)

    def _handler(self, signum, frame):
        if self.done.is_set():        # main has returned: a late repeat is ignored
            return
        if self.pending is None:
            self.pending = signum
            threading.Thread(target=self._repeat, args=(threading.main_thread().ident,),
                             daemon=True).start()
        raise KeyboardInterrupt() if self.pending == signal.SIGINT else Terminated()

    def _repeat(self, ident: int) -> None:
        while not self.done.wait(self.REPEAT_S):
            signal.pthread_kill(ident, self.pending)


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
    interrupts = _Interrupts()
    interrupts.install()
    try:
        try:
            status = _run(argv)
            if interrupts.pending is None or status == 0:
                return status
            signum = interrupts.pending    # an error that followed an interrupt is the interrupt's
        except BaseException as exc:
            if interrupts.pending is None and not isinstance(exc, (KeyboardInterrupt, Terminated)):
                raise
            signum = interrupts.pending or (signal.SIGTERM if isinstance(exc, Terminated) else signal.SIGINT)
        interrupts.done.set()
        print(f"faceplan: {'interrupted' if signum == signal.SIGINT else 'terminated'}; "
              "nothing was written", file=sys.stderr)
        return EXIT_INTERRUPTED if signum == signal.SIGINT else 128 + signal.SIGTERM
    finally:
        interrupts.restore()


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
