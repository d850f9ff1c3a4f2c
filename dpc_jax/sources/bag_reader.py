"""Reading a recording's messages with ``rosbags``, whatever its format (a ROS 1 bag, a ROS 2 bag folder, an
MCAP or SQLite file): each failure one line naming the recording (:class:`BagError`)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any


class BagError(ValueError):
    """A recording that cannot be used: one line naming it and what was expected."""


@contextmanager
def open_reader(path: Path) -> Iterator[Any]:
    """An open ``rosbags`` reader of ``path``; whatever it raises becomes one line naming the recording."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except BagError:
        raise
    except Exception as error:  # rosbags' errors differ by format (truncated, no footer, not a bag)
        if "end magic" in str(error):  # rosbags' words for an MCAP file without its footer
            raise BagError(f"{path}: the MCAP file has no footer: the recording was cut short (its recorder "
                         "did not close it); expected a complete file (`mcap recover` writes one)") from None
        raise BagError(f"{path}: cannot read the recording ({_words(error)}); expected a ROS 1 .bag, a ROS 2 "
                     "bag folder or an .mcap/.db3 file") from None
    try:
        yield reader
    finally:
        reader.close()


def _words(error: BaseException) -> str:
    text = " ".join(str(error).split()) or type(error).__name__
    return text[:200]


def read_messages(reader: Any, path: Path, connections: list[Any]) -> Iterator[tuple[Any, int, Any]]:
    """``(connection, message number on its topic, message)`` in the recording's order; a recording that
    breaks off (truncated, no MCAP footer) is one line."""
    numbers: dict[str, int] = {}
    try:
        for connection, _, raw in reader.messages(connections=connections):
            number = numbers.get(connection.topic, 0)
            numbers[connection.topic] = number + 1
            yield connection, number, reader.deserialize(raw, connection.msgtype)
    except Exception as error:  # rosbags' errors differ by format
        raise BagError(f"{path}: the recording breaks off ({_words(error)}); expected a complete recording "
                     "(was it cut short?)") from None
