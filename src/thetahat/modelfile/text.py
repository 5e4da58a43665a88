"""A model file's text, parsed: TOML or JSON into nested tables, with the limits of a hostile file.

The parsed document is checked against the key tables of :mod:`.keys` by :mod:`.schema`; here
only the syntax and the limits: brackets nested deeper than
:data:`~thetahat.limits.MAX_FILE_NESTING` (refused before a recursive parser sees them), a JSON
key given twice (refused as TOML refuses it), an integer too large for a float64, a byte-order
mark.
"""

from __future__ import annotations

import functools
import json
import sys
import tomllib
from typing import Any

from .. import limits
from ..errors import InputLimitError, ModelFileError

__all__ = ["parse_model_text"]

_FLOAT_MAX = int(sys.float_info.max)


def parse_model_text(text: str, syntax: str, source: str) -> dict[str, Any]:
    """The document of a model file's text.

    Parameters
    ----------
    text : str
        The file's content.
    syntax : {"toml", "json"}
    source : str
        The file's name, for the messages.

    Returns
    -------
    dict
        The top-level table.

    Raises
    ------
    ModelFileError
        Unknown syntax, text that is not valid TOML or JSON, a top level that is no table, a
        JSON key given twice, an integer too large for a float64.
    InputLimitError
        Brackets nested deeper than :data:`~thetahat.limits.MAX_FILE_NESTING`.

    Examples
    --------
    >>> from thetahat.modelfile.text import parse_model_text
    >>> parse_model_text('{"name": "x", "system": {"A": [[1]]}}', "json", "m.json")["system"]
    {'A': [[1]]}
    >>> parse_model_text('{"a": 1, "a": 2}', "json", "m.json")
    Traceback (most recent call last):
    ...
    thetahat.errors.ModelFileError: model file m.json: the key 'a' is given twice in one object; keep one.
    """
    if syntax not in ("toml", "json"):
        raise ModelFileError(f"model file {source}: unknown syntax {syntax!r}; use a .toml or "
                             f".json file (syntax 'toml' or 'json').")
    if not isinstance(text, str):
        raise ModelFileError(f"model file {source}: expected the file's text as a string; got "
                             f"{type(text).__name__}.")
    text = text.removeprefix("\ufeff")                   # a byte-order mark (Windows editors)
    _check_nesting(text, source)
    try:
        doc = tomllib.loads(text) if syntax == "toml" else \
            json.loads(text, object_pairs_hook=functools.partial(_json_object, source))
    except RecursionError as exc:
        raise InputLimitError(f"model file {source}: nested too deeply to parse.") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ModelFileError(f"model file {source} is not valid TOML: {exc}") from exc
    except json.JSONDecodeError as exc:
        raise ModelFileError(f"model file {source} is not valid JSON: {exc.msg} at line "
                             f"{exc.lineno}, column {exc.colno}.") from exc
    if not isinstance(doc, dict):
        raise ModelFileError(f"model file {source}: the top level must be a table (object).")
    _check_integers(doc, source, "")
    return doc


def _check_nesting(text: str, source: str) -> None:
    """Refuse brackets nested deeper than MAX_FILE_NESTING before a recursive parser sees them.

    Brackets inside strings and after ``#`` comments are skipped, so valid files are never
    refused by this scan.
    """
    depth = deepest = 0
    quote = ""
    comment = False
    escaped = False
    for ch in text:
        if comment:
            comment = ch != "\n"
        elif quote:
            if escaped:
                escaped = False
            elif ch == "\\" and quote == '"':
                escaped = True
            elif ch == quote or (ch == "\n" and quote == "'"):
                quote = ""
        elif ch in "\"'":
            quote = ch
        elif ch == "#":
            comment = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
            if deepest > limits.MAX_FILE_NESTING:
                raise InputLimitError(
                    f"model file {source}: tables or lists are nested deeper than "
                    f"{limits.MAX_FILE_NESTING} levels (thetahat.limits.MAX_FILE_NESTING); a "
                    f"model file needs at most 3 (a table holding a matrix).")
        elif ch in "]}":
            depth = max(0, depth - 1)


def _json_object(source: str, pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A JSON object; a key given twice is refused (as TOML does) instead of the last winning."""
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise ModelFileError(f"model file {source}: the key {key!r} is given twice in one "
                                 f"object; keep one.")
        out[key] = value
    return out


def _check_integers(value: Any, source: str, where: str) -> None:
    """Refuse integers that do not fit a float64 (a 400-digit number), naming the key."""
    stack = [(value, where)]
    while stack:
        item, at = stack.pop()
        if isinstance(item, dict):
            stack.extend((v, f"{at}.{k}" if at else str(k)) for k, v in item.items())
        elif isinstance(item, list):
            stack.extend((v, f"{at}[{i}]") for i, v in enumerate(item))
        elif isinstance(item, int) and not isinstance(item, bool) and abs(item) > _FLOAT_MAX:
            raise ModelFileError(f"model file {source}: {at}: the integer with "
                                 f"{len(str(abs(item)))} digits is too large for a float64 "
                                 f"number (at most about 1.8e308).")
