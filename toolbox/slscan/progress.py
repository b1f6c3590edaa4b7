"""Progress bars and console output on stderr for the command line (rich)."""

from __future__ import annotations

from typing import Self


def console():
    """A rich console on stderr (stdout stays free for tables and data)."""
    from rich.console import Console

    return Console(stderr=True)


class ProgressBar:
    """A rich progress bar on stderr; a no-op when ``quiet``.

    ``step(label)`` advances by one; ``update(done, total, label)`` sets the position.
    """

    def __init__(self, total: int, description: str, quiet: bool = False) -> None:
        self.quiet = quiet
        if quiet:
            return
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        self._progress = Progress(
            TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
            TextColumn("{task.fields[label]}"), TimeElapsedColumn(), TimeRemainingColumn(),
            console=console(), transient=False,
        )
        self._task = self._progress.add_task(description, total=total, label="")

    def __enter__(self) -> Self:
        if not self.quiet:
            self._progress.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if not self.quiet:
            self._progress.__exit__(*exc)

    def step(self, label: str = "") -> None:
        """Advance by one; a task that outgrows its estimated total (a stage's size is a
        guess before it runs: pairs to register, textures to bake) grows the total with it
        rather than showing more done than there is (``17/12``)."""
        if not self.quiet:
            task = next(t for t in self._progress.tasks if t.id == self._task)
            grow = {} if task.total is None or task.completed + 1 <= task.total else {"total": task.completed + 1}
            self._progress.update(self._task, advance=1, label=label, **grow)

    def update(self, done: int, total: int, label: str = "") -> None:
        if not self.quiet:
            self._progress.update(self._task, completed=done, total=total, label=label)

    def set(self, done: int, total: int) -> None:
        self.update(done, total)

    def set_total(self, total: int) -> None:
        """Change the number of steps (once the work turns out to be more or less)."""
        if not self.quiet:
            self._progress.update(self._task, total=total)
