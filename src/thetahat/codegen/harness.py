"""The generated command-line harness ``<name>_main.c`` and the ``Makefile`` that builds it.

The harness reads the CSV layout ``thetahat estimate`` reads (a header row with ``t``, one
column per input and per output, named as in the model or ``u1``…/``y1``… — ``u``/``y`` when
there is one; any order, other columns ignored) and writes the columns ``thetahat estimate``
writes (:func:`estimate_columns`), one row per sample, streaming: it holds one line at a time and
allocates nothing. The samples must be spaced by dt to the relative accuracy
:data:`~thetahat.estimation.observer.plan.DT_RTOL` (as for every fixed-step back end).

What lives here: the harness's and the Makefile's text, and the compiler flags. What it may
import: the observer's plan (for ``DT_RTOL``) and the text rules of :mod:`.c_text`.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

from ..estimation.observer.plan import DT_RTOL
from .c_text import comment_text, string_content, string_literal

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


_MAIN = r"""/* @P@_main.c -- CSV harness of the generated observer @P@ (thetahat codegen).
 *
 *   @P@ DATA.csv [--theta0 v1,v2,...] > estimates.csv
 *
 * DATA.csv: what `thetahat estimate` reads: UTF-8 (a byte-order mark is skipped), LF or CRLF,
 * fields quoted or not, lines of any length; a header row with t, the inputs (@INPUTS@) and
 * the outputs (@OUTPUTS@), named as in the model or u1.../y1... (any order; other columns
 * are ignored); one row per sample, spaced by dt = @DT@ s; an empty, NaN or NA output cell
 * is a missing sample (nan_policy). Writes the columns of `thetahat estimate` to stdout; "-"
 * reads stdin. Streaming: one record at a time, nothing allocated.
 * Exit codes: 0 success, 2 bad input, 3 the observer refused a sample, 4 the output could not
 * be written (message on stderr).
 */
#include <float.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <math.h>

#include "@P@.h"

/* Longest kept field (a header name or a number); other fields may be of any length. */
#define FIELD_MAX 255
/* The columns read: t, the inputs, the outputs. */
#define NCOLS (1 + @PU@_NU + @PU@_NY)

typedef @P@_real_t real_t;

/* Names a column may have, in order of preference (NULL-terminated). */
static const char *const ALIASES[NCOLS][4] = {{"t", NULL, NULL, NULL}, @ALIASES@};
static const char *const COLUMNS[] = {@COLUMNS@};
static const char *const MISSING[] = {"", "nan", "na", "n/a", "null", "none"};
static const double DT = @DT@;
static const double DT_RTOL = @DT_RTOL@;

static char cells[NCOLS][FIELD_MAX + 1];
static char field[FIELD_MAX + 1];

static int fail(const char *path, long lineno, const char *what)
{
    fprintf(stderr, "@P@: error: %s, line %ld: %s\n", path, lineno, what);
    return 2;
}

static int refused(const char *path, long lineno, int status)
{
    fflush(stdout);
    fprintf(stderr, "@P@: error: %s, line %ld: %s\n", path, lineno, @P@_error_message(status));
    return 3;
}

static void trim(char *s)
{
    char *start = s, *end;
    while (*start == ' ' || *start == '\t') {
        ++start;
    }
    end = start + strlen(start);
    while (end > start && (end[-1] == ' ' || end[-1] == '\t' || end[-1] == '\r')) {
        --end;
    }
    memmove(s, start, (size_t)(end - start));
    s[end - start] = '\0';
}

/* One CSV record (RFC 4180 quotes; LF or CRLF), field by field through `field` (unquoted,
 * trimmed). The header (header != 0) sets cols[k] to the field of column k's most preferred
 * alias (rank[k]); a data row copies the fields cols[] names into cells[] (*toolong: one was
 * longer than FIELD_MAX). Returns the number of fields, 0 for a blank line, -1 at the end of
 * the input, -2 for an unterminated quote. */
static int read_record(FILE *in, int header, int cols[], int rank[], int *toolong)
{
    int c, n = 0, len = 0, quoted = 0, over = 0, blank = 1, k, a;
    *toolong = 0;
    for (;;) {
        c = getc(in);
        if (c == EOF && n == 0 && len == 0 && blank && !quoted) {
            return -1;
        }
        if (quoted) {
            if (c == EOF) {
                return -2;
            }
            if (c == '"') {
                c = getc(in);
                if (c != '"') {
                    quoted = 0;
                    if (c != EOF) {
                        ungetc(c, in);
                    }
                    continue;
                }
            }
        } else if (c == '"') {
            quoted = 1;
            blank = 0;
            len = 0;
            continue;
        } else if (c == ',' || c == '\n' || c == EOF) {
            field[len] = '\0';
            trim(field);
            for (k = 0; k < NCOLS; ++k) {
                if (header) {
                    for (a = 0; a < 4 && ALIASES[k][a] != NULL && a < rank[k]; ++a) {
                        if (!over && strcmp(field, ALIASES[k][a]) == 0) {
                            rank[k] = a;
                            cols[k] = n;
                            break;
                        }
                    }
                } else if (cols[k] == n) {
                    if (over) {
                        *toolong = 1;
                    }
                    strcpy(cells[k], field);
                }
            }
            ++n;
            len = 0;
            over = 0;
            if (c != ',') {
                return (n == 1 && blank) ? 0 : n;
            }
            continue;
        }
        if (c != ' ' && c != '\t' && c != '\r') {
            blank = 0;
        }
        if (len < FIELD_MAX) {
            field[len++] = (char)c;
        } else {
            over = 1;
        }
    }
}

static int parse_real(const char *text, double *out)
{
    char *end;
    if (*text == '\0') {
        return 0;
    }
    *out = strtod(text, &end);
    return *end == '\0';
}

/* An output cell: a number, or a missing sample (NaN). */
static int parse_output(const char *text, double *out)
{
    char lower[8];
    size_t i, n = strlen(text);
    if (n < sizeof lower) {
        for (i = 0; i <= n; ++i) {
            lower[i] = (char)(text[i] >= 'A' && text[i] <= 'Z' ? text[i] - 'A' + 'a' : text[i]);
        }
        for (i = 0; i < sizeof MISSING / sizeof MISSING[0]; ++i) {
            if (strcmp(lower, MISSING[i]) == 0) {
                *out = NAN;
                return 1;
            }
        }
    }
    return parse_real(text, out);
}

static void print_row(double t, const @P@_state *s, const real_t phi[])
{
    int i;
    printf("%.@DIGITS@g", t);
    for (i = 0; i < @PU@_NX; ++i) {
        printf(",%.@DIGITS@g", (double)@P@_x_hat(s)[i]);
    }
    for (i = 0; i < @PU@_NK; ++i) {
        printf(",%.@DIGITS@g", (double)phi[i]);
    }
    for (i = 0; i < @PU@_NP; ++i) {
        printf(",%.@DIGITS@g", (double)@P@_theta_hat(s)[i]);
    }
@PRINT_SECOND@    printf("\n");
}

/* The estimates reached stdout (a full disk or a closed pipe is an error, exit 4). */
static int written(void)
{
    if (fflush(stdout) != 0 || ferror(stdout)) {
        fprintf(stderr, "@P@: error: cannot write the estimates to the standard output\n");
        return 4;
    }
    return 0;
}

int main(int argc, char **argv)
{
    const char *path = NULL;
    real_t theta0[@PU@_NP], u[@PU@_NU > 0 ? @PU@_NU : 1], y[@PU@_NY], phi[@PU@_NK];
    int cols[NCOLS], rank[NCOLS], have_theta0 = 0, toolong;
#if @FOH@
    real_t u_prev[@PU@_NU > 0 ? @PU@_NU : 1], y_prev[@PU@_NY];
#endif
    int i, c, nfields, nheader = -1, status, rows = 0;
    long lineno = 0;
    double t = 0, t_prev = 0, value;
    @P@_state state;
    FILE *in;
    for (i = 1; i < argc; ++i) {
        if (strcmp(argv[i], "--theta0") == 0 && i + 1 < argc) {
            char *cursor = argv[++i];
            int j;
            for (j = 0; j < @PU@_NP; ++j) {
                char *end;
                theta0[j] = (real_t)strtod(cursor, &end);
                if (end == cursor || (j + 1 < @PU@_NP ? *end != ',' : *end != '\0')) {
                    fprintf(stderr, "@P@: error: --theta0 needs @PU@_NP = %d comma-separated "
                            "numbers, e.g. --theta0 @THETA_EXAMPLE@\n", @PU@_NP);
                    return 2;
                }
                cursor = end + 1;
            }
            have_theta0 = 1;
        } else if (path == NULL && (argv[i][0] != '-' || strcmp(argv[i], "-") == 0)) {
            path = argv[i];
        } else {
            fprintf(stderr, "usage: @P@ DATA.csv [--theta0 v1,v2,...]\n");
            return 2;
        }
    }
    if (path == NULL) {
        fprintf(stderr, "usage: @P@ DATA.csv [--theta0 v1,v2,...]\n");
        return 2;
    }
    in = strcmp(path, "-") == 0 ? stdin : fopen(path, "rb");
    if (in == NULL) {
        fprintf(stderr, "@P@: error: cannot open %s\n", path);
        return 2;
    }
    status = @P@_init(&state, have_theta0 ? theta0 : NULL, NULL);
    if (status != @PU@_OK) {
        fprintf(stderr, "@P@: error: --theta0: %s\n", @P@_error_message(status));
        return 2;
    }
    c = getc(in);                                       /* a UTF-8 byte-order mark */
    if (c == 0xEF) {
        if (getc(in) != 0xBB || getc(in) != 0xBF) {
            return fail(path, 1, "not a UTF-8 CSV file");
        }
    } else if (c != EOF) {
        ungetc(c, in);
    }
    for (i = 0; i < NCOLS; ++i) {
        cols[i] = -1;
        rank[i] = 4;
    }
    u[0] = 0;
    for (;;) {
        nfields = read_record(in, nheader < 0, cols, rank, &toolong);
        ++lineno;
        if (nfields == -1) {
            break;
        }
        if (nfields == -2) {
            return fail(path, lineno, "a quoted field is not closed");
        }
        if (nfields == 0) {
            continue;
        }
        if (nheader < 0) {
            nheader = nfields;
            if (cols[0] < 0) {
                return fail(path, lineno, "missing column t");
            }
            for (i = 1; i < NCOLS; ++i) {
                if (cols[i] < 0) {
                    return fail(path, lineno, i <= @PU@_NU ? "missing input column (@INPUTS_S@)"
                                                           : "missing output column (@OUTPUTS_S@)");
                }
            }
            for (i = 0; i < (int)(sizeof COLUMNS / sizeof COLUMNS[0]); ++i) {
                printf(i ? ",%s" : "%s", COLUMNS[i]);
            }
            printf("\n");
            continue;
        }
        if (nfields != nheader) {
            return fail(path, lineno, "the number of fields differs from the header's");
        }
        if (toolong) {
            return fail(path, lineno, "a number is longer than 255 characters");
        }
        if (!parse_real(cells[0], &t) || !isfinite(t)) {
            return fail(path, lineno, "t is not a finite number");
        }
        /* the spacing to dt, relative to dt, allowing the rounding of t itself: a uniform
         * grid far from 0 (t = 8192 s at 1 kHz) has spacings off by an ulp of t */
        if (rows > 0 && !(fabs((t - t_prev) - DT) <= DT_RTOL * DT + 4 * DBL_EPSILON * fabs(t))) {
            return fail(path, lineno, "t is not spaced by the generated dt; resample the data "
                                      "or generate again with thetahat codegen --dt");
        }
        for (i = 0; i < @PU@_NU; ++i) {
            if (!parse_real(cells[1 + i], &value)) {
                return fail(path, lineno, "an input is not a number");
            }
            u[i] = (real_t)value;
        }
        for (i = 0; i < @PU@_NY; ++i) {
            if (!parse_output(cells[1 + @PU@_NU + i], &value)) {
                return fail(path, lineno, "an output is not a number (NaN marks a missing one)");
            }
            y[i] = (real_t)value;
        }
#if @START@
        if (rows == 0) {
            @P@_start_from_y(&state, y);
        }
#endif
#if @FOH@
        if (rows > 0) {     /* first-order hold: the step from the previous row to this one */
            status = @P@_phi_hat(&state, u_prev, y_prev, phi);
            if (status == @PU@_OK) {
                print_row(t_prev, &state, phi);
                status = @P@_step(&state, u_prev, y_prev, u, y);
            }
            if (status != @PU@_OK) {
                return refused(path, lineno - 1, status);
            }
        }
        for (i = 0; i < @PU@_NY; ++i) {
            y_prev[i] = y[i];
        }
        for (i = 0; i < (@PU@_NU > 0 ? @PU@_NU : 1); ++i) {
            u_prev[i] = u[i];
        }
#else
        status = @P@_phi_hat(&state, u, y, phi);
        if (status == @PU@_OK) {
            print_row(t, &state, phi);
            status = @P@_step(&state, u, y);
        }
        if (status != @PU@_OK) {
            return refused(path, lineno, status);
        }
#endif
        t_prev = t;
        ++rows;
        if (ferror(stdout)) {
            return written();
        }
    }
#if @FOH@
    if (rows > 0) {
        status = @P@_phi_hat(&state, u_prev, y_prev, phi);
        if (status != @PU@_OK) {
            return refused(path, lineno, status);
        }
        print_row(t_prev, &state, phi);
    }
#endif
    if (in != stdin) {
        fclose(in);
    }
    if (nheader < 0 || rows == 0) {
        return fail(path, lineno, "no header or no data rows");
    }
    return written();
}
"""


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
              "DIGITS": "17" if real == "double" else "9", "FOH": "1" if foh else "0",
              "START": "1" if start_from_y else "0", "PU": prefix.upper(), "P": prefix}
    # one pass: a value is never read again for placeholders (print_second's own are
    # substituted by a second pass over that text alone)
    values["PRINT_SECOND"] = _fill(print_second, values)
    return _fill(_MAIN, values)


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
