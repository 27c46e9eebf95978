"""Files the library writes whole or not at all, and fingerprints of their tensor content.

:func:`write_atomic` / :func:`save_atomic` write through a temporary file beside the target and
:func:`os.replace` it into place, so a reader (or a run killed while writing) never sees half a file.
:func:`update_digest` feeds one named tensor into a hash, the single way the policy files' weight checksum and
a resumed run's pre-training fingerprint are computed; :func:`code_digest` is the fingerprint of a module's code,
blind to its docstrings, comments and layout.
"""

from __future__ import annotations

import ast
import hashlib
import io
import os
from pathlib import Path
from typing import Any

import torch


def write_atomic(path: str | os.PathLike, data: bytes | str) -> None:
    """Write ``data`` (text as UTF-8) to ``path`` through ``<path>.tmp``; parent folders are created.

    Examples:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "out" / "note.txt"
        >>> write_atomic(path, "done")
        >>> path.read_text(), path.with_name("note.txt.tmp").exists()
        ('done', False)
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_bytes(data.encode() if isinstance(data, str) else data)
        os.replace(tmp, path)
    except BaseException:  # a full disk or an interrupt: no half-written temporary file stays behind
        tmp.unlink(missing_ok=True)
        raise


def save_atomic(obj: Any, path: str | os.PathLike) -> None:
    """``torch.save(obj)`` to ``path`` with :func:`write_atomic`."""
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    write_atomic(path, buffer.getvalue())


def update_digest(digest, name: str, value: torch.Tensor) -> None:
    """Feed ``name``, ``value``'s dtype and shape, then its bytes into ``digest`` (a :mod:`hashlib` object).

    Examples:
        >>> import hashlib
        >>> a, b = hashlib.sha256(), hashlib.sha256()
        >>> update_digest(a, "w", torch.zeros(2)); update_digest(b, "w", torch.zeros(2, 1))
        >>> a.hexdigest() == b.hexdigest()  # same bytes, another shape
        False
    """
    value = value.detach().cpu().contiguous()
    digest.update(f"{name}/{value.dtype}/{list(value.shape)}".encode())
    digest.update(value.reshape(-1).view(torch.uint8).numpy() if value.numel() else b"")


def code_digest(path: str | os.PathLike) -> str:
    """The SHA-256 of a Python file's code: its syntax tree without docstrings, so that editing a docstring or a
    comment, or reformatting, leaves it unchanged, and changing what the code does changes it.

    Examples:
        >>> import tempfile
        >>> folder = Path(tempfile.mkdtemp())
        >>> def digest(text):
        ...     _ = (folder / "m.py").write_text(text)
        ...     return code_digest(folder / "m.py")
        >>> plain = digest("def f(x):\\n    return 2 * x\\n")
        >>> digest("def f(x):\\n    'Twice x.'\\n    return 2*x  # doubled\\n") == plain  # docstring, comment, layout
        True
        >>> digest("def f(x):\\n    return 3 * x\\n") == plain
        False
    """
    tree = ast.parse(Path(path).read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (
            isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
            and body
            and isinstance(body[0], ast.Expr)
            and isinstance(body[0].value, ast.Constant)
            and isinstance(body[0].value.value, str)
        ):
            node.body = body[1:] or [ast.Pass()]
    return hashlib.sha256(ast.dump(tree, include_attributes=False).encode()).hexdigest()
