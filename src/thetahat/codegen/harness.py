"""The generated command-line harness ``<name>_main.c`` and the ``Makefile`` that builds it.

The harness reads the CSV layout ``thetahat estimate`` reads (a header row with ``t``, one
column per input and per output, named as in the model or ``u1``…/``y1``… — ``u``/``y`` when
there is one; any order, other columns ignored) and writes the columns ``thetahat estimate``
writes (:func:`estimate_columns`), one row per sample, streaming: it holds one line at a time and
allocates nothing.
"""

from __future__ import annotations

from collections.abc import Sequence

__all__ = ["C_FLAGS", "DT_RTOL", "estimate_columns", "harness_source", "makefile_source"]

#: The flags the generated code is checked with, and the Makefile's default.
C_FLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2")
#: The samples must be spaced by dt to this relative accuracy (as for the compiled kernel).
DT_RTOL = 1e-9


def estimate_columns(state_names: Sequence[str], k: int, parameter_names: Sequence[str], *,
                     refined: bool) -> tuple[str, ...]:
    """Header of an estimates CSV: t, x_hat_<x>…, phi_hat_<i>…, theta_hat_<θ>…, x_hat_refined_<x>….

    The same names as :func:`thetahat.datafile.estimate_columns` (a test checks it).

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
    return ", ".join('"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"' for s in items)


_MAIN = r"""/* @P@_main.c -- CSV harness of the generated observer @P@ (thetahat codegen).
 *
 *   @P@ DATA.csv [--theta0 v1,v2,...] > estimates.csv
 *
 * DATA.csv: a header row with t, the inputs (@INPUTS@) and the outputs (@OUTPUTS@), named as
 * in the model or u1.../y1... (any order; other columns are ignored); one row per sample,
 * spaced by dt = @DT@ s. Writes the columns of `thetahat estimate` to stdout. "-" reads stdin.
 * Exit codes: 0 success, 2 bad input, 3 the observer refused a sample (message on stderr).
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <math.h>

#include "@P@.h"

#define LINE_MAX_CHARS 65536
#define MAX_FIELDS 1024

typedef @P@_real_t real_t;

#if @PU@_NU > 0
static const char *const IN_ALIASES[][3] = {@IN_ALIASES@};
#endif
static const char *const OUT_ALIASES[][3] = {@OUT_ALIASES@};
static const char *const COLUMNS[] = {@COLUMNS@};
static const double DT = @DT@;
static const double DT_RTOL = @DT_RTOL@;

static char line[LINE_MAX_CHARS];
static char *fields[MAX_FIELDS];

static int fail(const char *path, long lineno, const char *what)
{
    fprintf(stderr, "@P@: error: %s, line %ld: %s\n", path, lineno, what);
    return 2;
}

/* Split line in place at commas; trims blanks; returns the number of fields. */
static int split(char *s)
{
    int count = 0;
    char *start = s, *end;
    for (;;) {
        char *comma = strchr(start, ',');
        if (comma != NULL) {
            *comma = '\0';
        }
        while (*start == ' ' || *start == '\t') {
            ++start;
        }
        end = start + strlen(start);
        while (end > start && (end[-1] == ' ' || end[-1] == '\t' || end[-1] == '\r'
                               || end[-1] == '\n')) {
            *--end = '\0';
        }
        if (count < MAX_FIELDS) {
            fields[count] = start;
        }
        ++count;
        if (comma == NULL) {
            return count;
        }
        start = comma + 1;
    }
}

static int find(int nfields, const char *const aliases[3])
{
    int a, i;
    for (a = 0; a < 3 && aliases[a] != NULL; ++a) {
        for (i = 0; i < nfields && i < MAX_FIELDS; ++i) {
            if (strcmp(fields[i], aliases[a]) == 0) {
                return i;
            }
        }
    }
    return -1;
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

static int refused(const char *path, long lineno, int status)
{
    fflush(stdout);
    fprintf(stderr, "@P@: error: %s, line %ld: %s\n", path, lineno, @P@_error_message(status));
    return 3;
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

int main(int argc, char **argv)
{
    const char *path = NULL;
    real_t theta0[@PU@_NP], u[@PU@_NU > 0 ? @PU@_NU : 1], y[@PU@_NY], phi[@PU@_NK];
#if @FOH@
    real_t u_prev[@PU@_NU > 0 ? @PU@_NU : 1], y_prev[@PU@_NY];
#endif
    int col_t, col_y[@PU@_NY], have_theta0 = 0;
#if @PU@_NU > 0
    int col_u[@PU@_NU];
#endif
    int i, nfields, nheader = -1, status, rows = 0;
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
    in = strcmp(path, "-") == 0 ? stdin : fopen(path, "r");
    if (in == NULL) {
        fprintf(stderr, "@P@: error: cannot open %s\n", path);
        return 2;
    }
    status = @P@_init(&state, have_theta0 ? theta0 : NULL, NULL);
    if (status != @PU@_OK) {
        fprintf(stderr, "@P@: error: --theta0: %s\n", @P@_error_message(status));
        return 2;
    }
    col_t = -1;
#if @PU@_NU > 0
    for (i = 0; i < @PU@_NU; ++i) {
        col_u[i] = 0;
    }
#endif
    u[0] = 0;
    for (i = 0; i < @PU@_NY; ++i) {
        col_y[i] = 0;
    }
    while (fgets(line, sizeof line, in) != NULL) {
        ++lineno;
        if (strchr(line, '\n') == NULL && !feof(in)) {
            return fail(path, lineno, "line too long");
        }
        nfields = split(line);
        if (nfields == 1 && fields[0][0] == '\0') {
            continue;
        }
        if (nfields > MAX_FIELDS) {
            return fail(path, lineno, "too many columns");
        }
        if (nheader < 0) {
            nheader = nfields;
            col_t = find(nfields, (const char *const[3]){"t", NULL, NULL});
#if @PU@_NU > 0
            for (i = 0; i < @PU@_NU; ++i) {
                col_u[i] = find(nfields, IN_ALIASES[i]);
                if (col_u[i] < 0) {
                    return fail(path, lineno, "missing input column (@INPUTS@)");
                }
            }
#endif
            for (i = 0; i < @PU@_NY; ++i) {
                col_y[i] = find(nfields, OUT_ALIASES[i]);
                if (col_y[i] < 0) {
                    return fail(path, lineno, "missing output column (@OUTPUTS@)");
                }
            }
            if (col_t < 0) {
                return fail(path, lineno, "missing column t");
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
        if (!parse_real(fields[col_t], &t) || !isfinite(t)) {
            return fail(path, lineno, "t is not a finite number");
        }
        if (rows > 0 && !(fabs((t - t_prev) - DT) <= DT_RTOL * DT)) {
            return fail(path, lineno, "t is not spaced by the generated dt; resample the data "
                                      "or generate again with thetahat codegen --dt");
        }
#if @PU@_NU > 0
        for (i = 0; i < @PU@_NU; ++i) {
            if (!parse_real(fields[col_u[i]], &value)) {
                return fail(path, lineno, "an input is not a number");
            }
            u[i] = (real_t)value;
        }
#endif
        for (i = 0; i < @PU@_NY; ++i) {
            if (!parse_real(fields[col_y[i]], &value)) {
                return fail(path, lineno, "an output is not a number (NaN marks a missing one)");
            }
            y[i] = (real_t)value;
        }
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
    return 0;
}
"""


def harness_source(prefix: str, names: dict[str, list[str]], k: int, real: str, second: bool,
                   dt: float, foh: bool = False) -> str:
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
    def aliases(group: str, letter: str) -> str:
        rows = _aliases(names[group], letter) or [[]]
        return ", ".join("{" + _c_strings(a) + ", NULL" * (3 - len(a)) + "}" for a in rows)

    cols = estimate_columns(names["x"], k, names["theta"], refined=second)
    print_second = ("    for (i = 0; i < @PU@_NX; ++i) {\n"
                    "        printf(\",%.@DIGITS@g\", (double)@P@_x_hat_refined(s)[i]);\n"
                    "    }\n" if second else "")
    text = _MAIN.replace("@PRINT_SECOND@", print_second)
    for key, value in (("@IN_ALIASES@", aliases("u", "u")),
                       ("@OUT_ALIASES@", aliases("y", "y")),
                       ("@COLUMNS@", _c_strings(cols)),
                       ("@INPUTS@", ", ".join(names["u"]) or "none"),
                       ("@OUTPUTS@", ", ".join(names["y"])),
                       ("@THETA_EXAMPLE@", ",".join("0.5" for _ in names["theta"])),
                       ("@DT_RTOL@", repr(DT_RTOL)), ("@DT@", repr(float(dt))),
                       ("@DIGITS@", "17" if real == "double" else "9"),
                       ("@FOH@", "1" if foh else "0"),
                       ("@PU@", prefix.upper()), ("@P@", prefix)):
        text = text.replace(key, value)
    return text


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
