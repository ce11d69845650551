"""Reading OpenCV FileStorage files (YAML, XML, JSON: rig calibrations) with every failure one line.

OpenCV's Python binding turns a file it cannot parse into ``SystemError: <class 'cv2.FileStorage'> returned
a result with an exception set`` (the ``cv2.error`` only as its cause), and a key of the wrong kind into an
assertion text (``isMap()``, ``nelems == m.total()*m.channels()``). :func:`read_storage` catches both and
raises :class:`ValueError` with the parser's own complaint and line ("line 7: Missing , between the
elements"); the caller puts its file name and error class in front.
"""

from __future__ import annotations

import os
import re

import cv2
import numpy as np

# "OpenCV(5.0.0) src.cpp:681: error: (-212:Parsing error) parseValue in function 'rig.yaml(7): Missing , …'"
# (a parsing error has its text where the function's name belongs) or "… (-215:Assertion failed) buf in
# function 'open'" (an assertion: the condition)
_CV_TEXT = re.compile(r"error: \((?P<code>-?\d+):[^)]*\)\s*(?P<cond>.*?) in function '(?P<func>.*)'\s*$",
                      re.S)
#: OpenCV's assertions on a bad file, in words
_ASSERTIONS = {
    "buf": "the file is empty",
    "nelems == m.total()*m.channels()": "a matrix whose data do not fit its rows and cols",
    "!dt.empty()": "a matrix without its element type (dt)",
}


def _reason(exc: BaseException, path: str) -> str:
    """The parser's complaint of ``exc`` (a cv2.error, or the SystemError around one) without OpenCV's
    source location: ``line N: text`` for a parsing error, the failed check in words for an assertion."""
    cause = exc if isinstance(exc, cv2.error) else (exc.__cause__ or exc.__context__ or exc)
    text = str(cause).strip()
    match = _CV_TEXT.search(text)
    if not match:
        return text or type(cause).__name__
    if match.group("code") == "-212":  # parsing error: "path(N): what"
        return re.sub(rf"^{re.escape(path)}\((\d+)\):\s*", r"line \1: ", match.group("func").strip())
    cond = match.group("cond").strip()
    return _ASSERTIONS.get(cond, f"OpenCV refused it ({cond})")


def read_storage(path: str | os.PathLike, keys: tuple[str, ...],
                 optional: tuple[str, ...] = ()) -> dict[str, np.ndarray | None]:
    """The values of ``keys`` in the FileStorage file ``path`` as float arrays (a matrix, a sequence of
    numbers or one number); an absent key of ``optional`` is None.

    :raises ValueError: no such file, not a FileStorage file (the parser's complaint and line), a key
        missing, or a key that holds no numbers (text, a map, a matrix whose data do not fit its shape).
    """
    path = str(path)
    if not os.path.isfile(path):
        raise ValueError("no such file")
    try:
        fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:
        raise ValueError(f"not an OpenCV FileStorage file (YAML, XML or JSON): {_reason(exc, path)}") \
            from None
    try:
        if not fs.isOpened():
            raise ValueError("not an OpenCV FileStorage file (YAML, XML or JSON)")
        if not fs.root().isMap():
            raise ValueError("not an OpenCV FileStorage file of named values (its top level is no map)")
        out: dict[str, np.ndarray | None] = {}
        for key in keys:
            try:
                node = fs.getNode(key)
                if node.empty() or node.isNone():
                    if key in optional:
                        out[key] = None
                        continue
                    raise ValueError(f"key {key} is missing")
                out[key] = _numbers(node, key)
            except (cv2.error, SystemError) as exc:
                raise ValueError(f"key {key}: {_reason(exc, path)}") from None
        return out
    finally:
        fs.release()


def _numbers(node: cv2.FileNode, key: str) -> np.ndarray:
    if node.isReal() or node.isInt():
        return np.array([node.real()], float)
    if node.isSeq():
        items = [node.at(i) for i in range(node.size())]
        if not all(item.isReal() or item.isInt() for item in items):
            raise ValueError(f"key {key} holds a sequence that is not all numbers")
        return np.array([item.real() for item in items], float)
    if node.isMap():
        value = node.mat()  # an !!opencv-matrix (a map in the file's grammar)
        if value is None:
            raise ValueError(f"key {key} holds a map, not a matrix")
        return np.asarray(value, float)
    raise ValueError(f"key {key} holds no numbers")
