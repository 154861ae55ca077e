"""Errors that the CLI maps to exit statuses: InputError -> 2, SolveError -> 3."""


class InputError(ValueError):
    """Bad user input. The message names the file and the field."""

    def __init__(self, message: str, *, file: str | None = None, field: str | None = None):
        where = ", ".join(x for x in (f"file {file}" if file else "", f"field {field}" if field else "") if x)
        super().__init__(f"{where}: {message}" if where else message)
        self.file = file
        self.field = field


class SolveError(RuntimeError):
    """The model could not be solved; the message says where and why."""
