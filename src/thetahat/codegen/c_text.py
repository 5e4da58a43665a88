"""Text that enters generated C: comments, string literals and the name of the observer.

Nothing from a model or a caller reaches the generated files raw. The rules, for C99 compiled
with ``-std=c99 -Wall -Wextra -Werror -pedantic`` (and ``-Wtrigraphs``):

Comments (:func:`comment_text`)
    One line: control characters, line and paragraph separators and Unicode format characters
    (the bidirectional overrides of "Trojan Source", zero-width joiners) are removed or become
    spaces, runs of white space one space. ``*/`` and ``/*`` become ``* /`` and ``/ *`` (the
    comment cannot end early nor nest), ``??`` becomes ``? ?`` (no trigraph: ``??/`` is a
    backslash), and trailing backslashes and spaces are dropped (no line splice). Other
    non-ASCII characters are kept as UTF-8: a comment is not translated, compilers accept
    UTF-8 there, and a model's title in Greek stays readable.
String literals (:func:`string_literal`)
    Printable ASCII is kept, except ``"``, ``\\`` and ``?`` (escaped: ``\\"``, ``\\\\``,
    ``\\?``, so no trigraph); every other byte of the UTF-8 text, non-ASCII included, is a
    three-digit octal escape, so the literal holds the same bytes under any compiler's source
    and execution character sets (a CSV header is compared byte for byte).
The name (:func:`check_c_name`, :func:`name_collisions`)
    The name is the stem of the files and the prefix of every public identifier (``<name>_step``,
    ``<NAME>_NX``). It must be an ASCII C identifier that starts with a letter (C reserves
    every name that starts with an underscore at file scope), of at most
    :data:`MAX_NAME_LENGTH` characters (C99 guarantees 31 significant characters of an
    external name; the longest public suffix is ``_x_hat_refined``), without ``__`` and not
    ending with ``_`` (C++ reserves ``__`` anywhere, and the header is C++'s too), not a C
    keyword (C99 to C23), not starting with ``str``, ``mem`` or ``wcs`` and a lowercase letter
    (reserved for ``<string.h>`` and ``<stdlib.h>``, C99 7.26.10–11, which the harness
    includes), and not ``clean``, ``makefile`` or ``gnumakefile`` in any case (a target of the
    generated ``Makefile``, and names ``make`` reads as its makefile). Last, the generated code's
    own identifiers: no identifier of the sources outside the public interface may start with
    ``<name>_`` or ``<NAME>_`` (``f`` would make the public ``f_phi_hat`` of a helper
    ``f_phi_hat``). An explicit name that breaks a rule is refused
    (:class:`~thetahat.errors.OptionError`, naming a name that passes); a name derived from a
    file stem (:func:`name_from_stem`) is made an identifier first.

What lives here: those functions and their limits. What it may import: the errors.
"""

from __future__ import annotations

import re
import unicodedata
from collections.abc import Iterable

from ..errors import ArgumentTypeError, OptionError

__all__ = ["C_KEYWORDS", "MAX_NAME_LENGTH", "check_c_name", "comment_text", "name_collisions",
           "name_from_stem", "name_problem", "refuse_collisions", "string_content",
           "string_literal", "suggest_name"]

#: Longest name: 31 (C99 5.2.4.1, significant initial characters of an external identifier)
#: less 7, so that ``<name>_x_hat`` and ``<name>_x_hat_refined`` differ within 31 characters.
MAX_NAME_LENGTH = 24

#: The keywords of C99, C11 and C23 (those that do not start with an underscore and a capital,
#: which the underscore rule refuses anyway).
C_KEYWORDS = frozenset("""
    auto break case char const continue default do double else enum extern float for goto if
    inline int long register restrict return short signed sizeof static struct switch typedef
    union unsigned void volatile while alignas alignof bool constexpr false nullptr
    static_assert thread_local true typeof typeof_unqual""".split())

#: Names the generated Makefile or ``make`` itself use (compared in lower case).
_MAKE_NAMES = frozenset({"clean", "makefile", "gnumakefile"})
_IDENT = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
_LIBRARY = re.compile(r"(str|mem|wcs)[a-z]")
#: Comments, string and character literals, and preprocessor include lines of C source.
_NOT_CODE = re.compile(r'/\*.*?\*/|//[^\n]*|"(?:\\.|[^"\\\n])*"|\'(?:\\.|[^\'\\\n])*\'|'
                       r'^[ \t]*#[ \t]*include[^\n]*', re.S | re.M)
_WORD = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
#: Unicode categories that never reach a comment: controls, format characters (bidirectional
#: overrides, zero-width joiners), surrogates, private use, unassigned, line/paragraph breaks.
_DROP = frozenset({"Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp"})


def comment_text(text: object) -> str:
    """``text`` made safe inside a C block comment, on one line (see the module docstring).

    Parameters
    ----------
    text : object
        Its ``str``.

    Returns
    -------
    str

    Examples
    --------
    >>> comment_text('demo */ int thetahat_injected = 1; /*')
    'demo * / int thetahat_injected = 1; / *'
    >>> comment_text("what??/\\nnext \\u202eline\\\\")
    'what? ?/ next line'
    """
    chars = (" " if ch.isspace() else "" if unicodedata.category(ch) in _DROP else ch
             for ch in str(text))
    out = " ".join("".join(chars).split())
    while True:
        before = out
        out = out.replace("??", "? ?").replace("*/", "* /").replace("/*", "/ *")
        out = out.rstrip(" \\")
        if out == before:
            return out


def string_content(text: object) -> str:
    """The characters between the quotes of a C string literal holding ``text``'s UTF-8 bytes.

    Parameters
    ----------
    text : object
        Its ``str``.

    Returns
    -------
    str

    Examples
    --------
    >>> print(string_content('a"b\\\\c??/é'))
    a\\"b\\\\c\\?\\?/\\303\\251
    """
    out = []
    for byte in str(text).encode("utf-8", "surrogatepass"):
        ch = chr(byte)
        if ch in '"\\?':
            out.append("\\" + ch)
        elif 0x20 <= byte < 0x7F:
            out.append(ch)
        else:
            out.append(f"\\{byte:03o}")
    return "".join(out)


def string_literal(text: object) -> str:
    """A C string literal holding ``text``'s UTF-8 bytes (:func:`string_content` in quotes).

    Parameters
    ----------
    text : object

    Returns
    -------
    str

    Examples
    --------
    >>> string_literal("theta_hat_ω")
    '"theta_hat_\\\\317\\\\211"'
    """
    return '"' + string_content(text) + '"'


def name_problem(name: str) -> str | None:
    """Why ``name`` cannot be the generated code's name (the static rules of the module
    docstring), or None.

    Parameters
    ----------
    name : str

    Returns
    -------
    str or None

    Examples
    --------
    >>> name_problem("lugre") is None, name_problem("clean")
    (True, 'the generated Makefile (or make itself) uses that name')
    """
    if not _IDENT.fullmatch(name):
        if name[:1] == "_":
            return "it starts with an underscore, which C reserves at file scope"
        if name[:1].isdigit():
            return "a C identifier cannot start with a digit"
        return ("a C identifier has ASCII letters, digits and underscores only"
                if name else "it is empty")
    if len(name) > MAX_NAME_LENGTH:
        return (f"it has {len(name)} characters, more than {MAX_NAME_LENGTH} (C99 guarantees "
                "31 significant characters of an external name, and the longest public name "
                "adds '_x_hat_refined')")
    if "__" in name or name.endswith("_"):
        return "C and C++ reserve names with a double underscore (<name>_step would have one)"
    if name in C_KEYWORDS:
        return "it is a C keyword"
    if _LIBRARY.match(name):
        return ("external names that start with 'str', 'mem' or 'wcs' and a lowercase letter "
                "are reserved for <string.h> and <stdlib.h> (C99 7.26.10-11)")
    if name.lower() in _MAKE_NAMES:
        return "the generated Makefile (or make itself) uses that name"
    return None


def suggest_name(name: str, collides: Iterable[str] = ()) -> str:
    """A name that passes the static rules, close to ``name`` and not in ``collides``.

    Parameters
    ----------
    name : str
    collides : iterable of str
        Names to avoid (the generated code's own identifiers).

    Returns
    -------
    str

    Examples
    --------
    >>> suggest_name("demo */ x"), suggest_name("stream")
    ('demo_x_obs', 'obs_stream')
    """
    base = re.sub(r"[^A-Za-z0-9_]+", "_", name)
    base = re.sub(r"_+", "_", base).strip("_")[:MAX_NAME_LENGTH - 4] or "observer"
    for cand in (f"{base}_obs", f"obs_{base}", "observer"):
        cand = re.sub(r"_+", "_", cand)
        if name_problem(cand) is None and cand not in collides:
            return cand
    return "observer"


def check_c_name(name: object) -> str:
    """``name`` if it may be the generated code's name and prefix (the static rules of the
    module docstring), else an :class:`~thetahat.errors.OptionError` that names one that may.

    Parameters
    ----------
    name : str

    Returns
    -------
    str
        ``name`` unchanged.

    Raises
    ------
    ArgumentTypeError
        Not a string.
    OptionError
        A rule fails.

    Examples
    --------
    >>> check_c_name("lugre")
    'lugre'
    >>> check_c_name("demo */ int x; /*")
    Traceback (most recent call last):
    ...
    thetahat.errors.OptionError: the C name 'demo */ int x; /*' (name=, --name on the command line) cannot be used: a C identifier has ASCII letters, digits and underscores only; choose another, e.g. 'demo_int_x_obs'.
    """
    if not isinstance(name, str):
        raise ArgumentTypeError(f"name must be a string (the C identifier's stem, e.g. "
                                f"'lugre'); got {type(name).__name__}.")
    problem = name_problem(name)
    if problem is not None:
        raise OptionError(f"the C name {name!r} (name=, --name on the command line) cannot be "
                          f"used: {problem}; choose another, e.g. {suggest_name(name)!r}.")
    return name


def name_from_stem(stem: str) -> str:
    """A C name from a file stem: lower case, each run of other characters one ``_``, a
    leading digit prefixed with ``obs_`` (the default name of ``thetahat codegen``).

    The result still has to pass :func:`check_c_name` (``clean.toml`` gives ``clean``).

    Parameters
    ----------
    stem : str

    Returns
    -------
    str

    Examples
    --------
    >>> name_from_stem("2-mass spring"), name_from_stem("LuGre")
    ('obs_2_mass_spring', 'lugre')
    """
    ident = re.sub(r"[^A-Za-z0-9]+", "_", stem).strip("_").lower()
    if not ident:
        return "observer"
    return "obs_" + ident if ident[0].isdigit() else ident


def name_collisions(name: str, header: str, sources: Iterable[str]) -> list[str]:
    """Identifiers of ``sources`` outside the public interface that start with ``<name>_``
    or ``<NAME>_`` (the generated code's own helpers ``name`` would collide with).

    Parameters
    ----------
    name : str
    header : str
        The generated header: its identifiers with the prefix are the public interface.
    sources : iterable of str
        The generated C sources (comments, strings and includes are not read).

    Returns
    -------
    list of str
        Sorted; empty when ``name`` is free.

    Examples
    --------
    >>> name_collisions("f", "int f_step(void);", ["static int f_helper(void);", "f_step();"])
    ['f_helper']
    """
    starts = (name + "_", name.upper() + "_")

    def words(text: str) -> set[str]:
        return {w for w in _WORD.findall(_NOT_CODE.sub(" ", text)) if w.startswith(starts)}

    public = words(header)
    return sorted(set().union(*(words(s) for s in sources)) - public)


def refuse_collisions(name: str, collisions: list[str]) -> None:
    """Raise the :class:`~thetahat.errors.OptionError` of :func:`name_collisions`' findings.

    Parameters
    ----------
    name : str
    collisions : list of str

    Raises
    ------
    OptionError
        ``collisions`` is not empty.
    """
    if collisions:
        shown = ", ".join(collisions[:4]) + (", ..." if len(collisions) > 4 else "")
        raise OptionError(f"the C name {name!r} (name=, --name on the command line) cannot be "
                          f"used: the generated code's own identifiers {shown} start with "
                          f"{name}_ as its public ones ({name}_init, {name}_step, ...) do, "
                          f"and could clash with them; choose another, e.g. "
                          f"{suggest_name(name, collisions)!r}.")
