"""The progress bar: a task that outgrows its estimated total."""

from __future__ import annotations

from slscan.progress import ProgressBar


def test_a_bar_grows_its_total_instead_of_overflowing():
    with ProgressBar(3, "texture") as bar:
        for _ in range(5):
            bar.step("x")
        task = bar._progress.tasks[0]
        assert (task.completed, task.total) == (5, 5)
    with ProgressBar(4, "decode") as bar:
        bar.step()
        task = bar._progress.tasks[0]
        assert (task.completed, task.total) == (1, 4)  # within the estimate: unchanged
    quiet = ProgressBar(1, "quiet", quiet=True)
    quiet.step()  # a no-op
