"""The generated command-line harness ``<name>_main.c`` and the ``Makefile`` that builds it.

The harness reads a CSV as ``thetahat estimate`` reads it, by the same rules (docs/bad-input.md,
"The rules of a record"; the template's comment lists them): UTF-8, LF/CRLF/CR, the separator
from the header, plain decimal cells, each name once, at least two rows. It differs where a
streaming program without a heap must: a number longer than 1023 characters is refused, a
``[data]`` table is not read, there is no limit on the file's size or rows, and the samples
must be spaced by dt to the relative accuracy
:data:`~thetahat.estimation.observer.plan.DT_RTOL` (as for every fixed-step back end). It
writes the columns ``thetahat estimate`` writes (:func:`estimate_columns`), one row per
sample, holding one record at a time and allocating nothing.

What lives here: the harness's and the Makefile's text (filled in from
:data:`~.harness_template.MAIN_TEMPLATE`), and the compiler flags. What it may import: the
observer's plan (for ``DT_RTOL``), the text rules of :mod:`.c_text` and the template.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

from ..estimation.observer.plan import DT_RTOL
from .c_text import comment_text, string_content, string_literal
from .harness_template import MAIN_TEMPLATE

__all__ = ["C_FLAGS", "estimate_columns", "harness_source", "makefile_source"]

#: The flags the generated code is checked with, and the Makefile's default.
C_FLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2")


def estimate_columns(state_names: Sequence[str], k: int, parameter_names: Sequence[str], *,
                     refined: bool) -> tuple[str, ...]:
    """Header of an estimates CSV: t, x_hat_<x>…, phi_hat_<i>…, theta_hat_<θ>…, x_hat_refined_<x>….

    The same names as :func:`thetahat.io.datafile.estimate_columns` (a test checks it).

    Parameters
    ----------
    state_names : sequence of str
    k : int
        Length of φ.
    parameter_names : sequence of str
    refined : bool
        Include the second observer's columns.

    Returns
    -------
    tuple of str

    Examples
    --------
    >>> estimate_columns(["x1", "x2"], 1, ["theta"], refined=False)
    ('t', 'x_hat_x1', 'x_hat_x2', 'phi_hat_1', 'theta_hat_theta')
    """
    cols = ["t"] + [f"x_hat_{s}" for s in state_names]
    cols += [f"phi_hat_{i + 1}" for i in range(k)]
    cols += [f"theta_hat_{s}" for s in parameter_names]
    if refined:
        cols += [f"x_hat_refined_{s}" for s in state_names]
    return tuple(cols)


def _aliases(names: Sequence[str], letter: str) -> list[list[str]]:
    out = []
    for i, name in enumerate(names):
        alts = [name, f"{letter}{i + 1}"] + ([letter] if len(names) == 1 else [])
        out.append(list(dict.fromkeys(alts)))
    return out


def _c_strings(items: Sequence[str]) -> str:
    return ", ".join(string_literal(s) for s in items)




def harness_source(prefix: str, names: dict[str, list[str]], k: int, real: str, second: bool,
                   dt: float, foh: bool = False, *, start_from_y: bool = False) -> str:
    """Source of ``<prefix>_main.c`` (see the module docstring).

    Parameters
    ----------
    prefix : str
        C prefix of the observer.
    names : dict
        Names of ``u``, ``y``, ``x`` and ``theta`` (lists of str).
    k : int
        Length of φ.
    real : {"double", "float"}
    second : bool
        A second observer is attached.
    dt : float
        The fixed step length.
    foh : bool
        The step takes the next samples (first-order hold): each row is printed when the
        next one has been read.
    start_from_y : bool
        Call ``<prefix>_start_from_y`` with the first row's outputs (x̂(0) = x̂₀ + C⁺(y(0) −
        C x̂₀), as the model file's estimators start).

    Returns
    -------
    str

    Examples
    --------
    >>> src = harness_source("obs", {"u": ["u"], "y": ["y"], "x": ["x1"], "theta": ["a"]}, 1,
    ...                      "double", False, 1e-3)
    >>> '"theta_hat_a"' in src and "malloc" not in src
    True
    """
    rows = _aliases(names["u"], "u") + _aliases(names["y"], "y")
    alias_text = ", ".join("{" + _c_strings(a) + ", NULL" * (4 - len(a)) + "}" for a in rows)

    cols = estimate_columns(names["x"], k, names["theta"], refined=second)
    print_second = ("    for (i = 0; i < @PU@_NX; ++i) {\n"
                    "        printf(\",%.@DIGITS@g\", (double)@P@_x_hat_refined(s)[i]);\n"
                    "    }\n" if second else "")
    inputs, outputs = ", ".join(names["u"]) or "none", ", ".join(names["y"])
    values = {"PRINT_SECOND": print_second, "ALIASES": alias_text, "COLUMNS": _c_strings(cols),
              "INPUTS": comment_text(inputs), "OUTPUTS": comment_text(outputs),
              "INPUTS_S": string_content(inputs), "OUTPUTS_S": string_content(outputs),
              "THETA_EXAMPLE": ",".join("0.5" for _ in names["theta"]),
              "DT_RTOL": repr(DT_RTOL), "DT": repr(float(dt)),
              "DIGITS": "17" if real == "double" else "9",
              "START": "1" if start_from_y else "0", "NEXT": ", u, y" if foh else "",
              "PU": prefix.upper(), "P": prefix}
    # one pass: a value is never read again for placeholders (print_second's own are
    # substituted by a second pass over that text alone)
    values["PRINT_SECOND"] = _fill(print_second, values)
    return _fill(MAIN_TEMPLATE, values)


def _fill(template: str, values: dict[str, str]) -> str:
    """``template`` with each ``@KEY@`` replaced by ``values[KEY]``, in one pass."""
    return re.sub(r"@([A-Z_]+)@", lambda m: values[m.group(1)], template)


def makefile_source(prefix: str) -> str:
    """The ``Makefile``: ``make -C DIR`` builds ``DIR/<prefix>`` with :data:`C_FLAGS`.

    Parameters
    ----------
    prefix : str

    Returns
    -------
    str

    Examples
    --------
    >>> print(makefile_source("obs").splitlines()[3])
    CFLAGS ?= -std=c99 -Wall -Wextra -Werror -pedantic -O2
    """
    return (f"# Generated by thetahat codegen: builds the CSV harness {prefix} of {prefix}.c.\n"
            "# Override e.g. CC=clang or CFLAGS='... -fsanitize=address,undefined'.\n"
            "CC ?= cc\n"
            f"CFLAGS ?= {' '.join(C_FLAGS)}\n"
            "LDLIBS ?= -lm\n\n"
            f"{prefix}: {prefix}_main.c {prefix}.c {prefix}.h\n"
            f"\t$(CC) $(CFLAGS) -o $@ {prefix}_main.c {prefix}.c $(LDLIBS)\n\n"
            ".PHONY: clean\n"
            f"clean:\n\trm -f {prefix}\n")
