"""Reading a checkpoint: a damaged file is reported by its name, not by a deep library error.

A truncated SB3 ``.zip``, a garbage ``.pt`` or a ``qos_policy.json`` that does not parse makes
torch, stable-baselines3 or json raise whatever they raise (``UnpicklingError``,
``AssertionError``, ``[Errno 22] Invalid argument``, ``Expecting value``), none of which says
which file is at fault. :func:`reading_checkpoint` turns them into one ``ValueError``:
``checkpoint 'path' is corrupt: <what the library said>``, with how to make it again.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

__all__ = ["reading_checkpoint"]

_MAX_CHARS = 200


@contextlib.contextmanager
def reading_checkpoint(path: str | Path, *, remedy: str = "") -> Iterator[None]:
    """Report any error raised inside the block as the checkpoint ``path`` being corrupt.

    ``remedy`` (e.g. ``"train it again with `codesign train b`"``) ends the message. Wrap
    only the reading (and parsing) of the file, after checking that it exists, so that a
    missing file keeps its own message.

    Examples
    --------
    >>> import json
    >>> try:
    ...     with reading_checkpoint("bad.json"):
    ...         json.loads("{")
    ... except ValueError as exc:
    ...     print(exc)  # doctest: +ELLIPSIS
    checkpoint 'bad.json' is corrupt: JSONDecodeError: Expecting property name ...
    """
    try:
        yield
    except Exception as exc:
        text = " ".join(str(exc).split()) or "no message"
        if len(text) > _MAX_CHARS:
            text = text[: _MAX_CHARS - 3] + "..."
        tail = f" ({remedy})" if remedy else ""
        raise ValueError(
            f"checkpoint {str(path)!r} is corrupt: {type(exc).__name__}: {text}{tail}"
        ) from exc
