"""Errors of the fuzzy engine: a rule file that is refused, and inputs that cannot be evaluated.

`fuzzy` stands alone (it imports nothing of the farm), so these do not derive from
`core.errors.QuekaroError`; callers that report to a user catch them by name.
"""

from __future__ import annotations


class RuleFileError(ValueError):
    """A rule file that cannot be read, is not valid XML, breaks the schema or is inconsistent.

    Carries the file, line, variable and label at fault (each `None` where it does not apply), and
    renders them all in its message so that a user can find the place to fix.
    """

    def __init__(
        self,
        message: str,
        *,
        file: str | None = None,
        line: int | None = None,
        variable: str | None = None,
        label: str | None = None,
    ) -> None:
        self.message = message
        self.file = file
        self.line = line
        self.variable = variable
        self.label = label
        super().__init__(self._render())

    def _render(self) -> str:
        where = self.file or "<rules>"
        if self.line is not None:
            where += f":{self.line}"
        parts = [where]
        if self.variable is not None:
            parts.append(f"variable {self.variable!r}")
        if self.label is not None:
            parts.append(f"label {self.label!r}")
        return ", ".join(parts) + f": {self.message}"


class FuzzyInputError(ValueError):
    """Inputs that cannot be evaluated: NaN, wrong shape, unknown or missing variables, bad ranges."""
