"""Bad input reaches the user as one line: the file (frame, option), what is wrong, what to do.

:class:`InputError` is the one exception type for a problem in what the user gave us (a data
folder, a ``transforms.json`` frame, an image, a command-line option, a checkpoint folder).
Every check that finds one raises it (or a subclass), with a message that names the thing and
says how to fix it. Our entry points (``seathru-*`` commands, :class:`~seathru_nerfstudio.
training.SeathruTrainer` under ``ns-train``, :class:`~seathru_nerfstudio.pipeline.SeathruPipeline`
under ``ns-eval``/``ns-render``/``ns-viewer``) turn it into that line on the console and exit
status 1, with no traceback: :func:`exit_on_input_error`. Any other exception is our bug and keeps
its traceback.
"""

from __future__ import annotations

import contextlib
from typing import Iterator, Type

EXIT_STATUS = 1
"""The exit status of a command stopped by an :class:`InputError`."""


class InputError(ValueError):
    """A problem in the user's input; the message names the file, frame or option and says what to
    do. Shown as one line with exit status 1 by our entry points (a ``ValueError``, so code that
    catches those still does)."""


def one_line(message: str) -> str:
    """``message`` with its line breaks folded, so that it prints (and greps) as one line."""
    return " ".join(part.strip() for part in str(message).splitlines() if part.strip())


def print_input_error(error: BaseException) -> None:
    """Print ``Error: <message>`` in red on nerfstudio's console, as one line at any terminal width."""
    from nerfstudio.utils.rich_utils import CONSOLE  # rich is already loaded wherever this runs
    from rich.text import Text

    # a Text, not markup: a message may hold brackets ("[0, 1]") that rich would read as tags
    CONSOLE.print(Text.assemble(("Error: ", "bold red"), one_line(str(error))), soft_wrap=True, highlight=False)


@contextlib.contextmanager
def exit_on_input_error(*also: Type[BaseException]) -> Iterator[None]:
    """Within this block, an :class:`InputError` (or one of the types ``also``: errors that are
    not the user's but need no traceback either) prints its one line and exits with
    :data:`EXIT_STATUS` (``SystemExit``, so ``finally`` blocks and exit handlers still run)."""
    try:
        yield
    except (InputError, *also) as error:
        print_input_error(error)
        raise SystemExit(EXIT_STATUS) from None
