"""An unexpected exception in a command is shown as a bug: the traceback, a line asking to
report it, exit status 1 (not 2, which means bad input), from the `faceplan` entry point;
`main` itself lets it propagate to a programmatic caller."""
import planner.cli as cli


def test_unexpected_exception_is_reported_as_a_bug(monkeypatch, capsys):
    def run(args):
        raise ZeroDivisionError("an internal slip")

    monkeypatch.setattr(cli._load("compare"), "run", run)
    assert cli.entry(["compare", "somewhere"]) == 1
    err = capsys.readouterr().err
    assert "ZeroDivisionError: an internal slip" in err and "Traceback" in err
    assert "this is a bug in faceplan: please report it" in err


def test_main_lets_a_bug_propagate(monkeypatch):
    import pytest

    def run(args):
        raise ZeroDivisionError("an internal slip")

    monkeypatch.setattr(cli._load("compare"), "run", run)
    with pytest.raises(ZeroDivisionError):
        cli.main(["compare", "somewhere"])
