"""The text of the generated CSV harness ``<name>_main.c``, with its ``@KEY@`` placeholders.

:func:`~thetahat.codegen.harness.harness_source` fills it in. The C reads a record by the rules
of ``thetahat estimate``'s reader (:mod:`thetahat.io.tables`, docs/bad-input.md "The rules of
a record"): a conformance test feeds both the same hostile files.

What lives here: :data:`MAIN_TEMPLATE`. What it may import: nothing.
"""

__all__ = ["MAIN_TEMPLATE"]

#: ``<name>_main.c`` with placeholders ``@P@``, ``@PU@``, ``@ALIASES@``, ``@COLUMNS@``, …
MAIN_TEMPLATE = r"""/* @P@_main.c -- CSV harness of the generated observer @P@ (thetahat codegen).
 *
 *   @P@ DATA.csv [--theta0 v1,v2,...] > estimates.csv
 *
 * DATA.csv: what `thetahat estimate` reads (docs/bad-input.md, "The rules of a record"):
 * UTF-8 (a byte-order mark is dropped; invalid UTF-8 anywhere is refused), lines ended by LF,
 * CRLF or CR, separated by a comma, a semicolon or a tab (the one that splits the header
 * into the most fields), fields quoted or not, lines of any length. The first line that is
 * not blank is the header, with t, the inputs (@INPUTS@) and the outputs (@OUTPUTS@), named
 * as in the model or u1.../y1... (u/y for one; any order; other columns are ignored; a name
 * used twice, or two names of one signal, are refused). Blank rows are skipped; every other
 * row has as many fields as the header. A cell is a plain decimal number (1e-3, inf, nan;
 * with a semicolon or tab separator a decimal comma, but not both marks in one file), in
 * optional spaces and quotes; a NUL byte, text, hexadecimal or digit separators are refused.
 * An empty, NaN, NA, N/A, NULL or NONE output cell is a missing sample (nan_policy); t and
 * the inputs must be finite, outputs not infinite. At least two rows, spaced by dt = @DT@ s.
 * Writes the columns of `thetahat estimate` to stdout; "-" reads stdin. Streaming: one
 * record at a time, nothing allocated; a number may have up to FIELD_MAX characters.
 * Exit codes: 0 success, 2 bad input, 3 the observer refused a sample, 4 the output could not
 * be written (message on stderr).
 */
#include <float.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <math.h>

#include "@P@.h"

/* Longest kept field (a header name or a number; every double written out exactly fits);
 * other fields may be of any length. */
#define FIELD_MAX 1023
/* The columns read: t, the inputs, the outputs. */
#define NCOLS (1 + @PU@_NU + @PU@_NY)
#define NALIAS 4
#define NUB (@PU@_NU > 0 ? @PU@_NU : 1)
/* What next_byte returns besides a byte: the end of the input, and a byte that breaks UTF-8. */
#define END_OF_INPUT (-1)
#define NOT_UTF8 (-3)

typedef @P@_real_t real_t;

/* Names a column may have, in order of preference (NULL-terminated). */
static const char *const ALIASES[NCOLS][NALIAS] = {{"t", NULL, NULL, NULL}, @ALIASES@};
static const char *const COLUMNS[] = {@COLUMNS@};
static const char *const MISSING[] = {"", "nan", "na", "n/a", "null", "none"};
static const char SEPARATORS[3] = {',', ';', '\t'};
static const double DT = @DT@;
static const double DT_RTOL = @DT_RTOL@;

enum { START, PLAIN, QUOTED, QUOTE };

/* A field as read: its first FIELD_MAX bytes; longer (over), holding text beyond them
 * (lost), holding a NUL byte (nul). */
typedef struct {
    char text[FIELD_MAX + 1];
    size_t len;
    int over, lost, nul;
} field_t;

/* A CSV reader for one separator: the header is read by three at once, one per separator,
 * and the one that finds the most fields reads the data. */
typedef struct {
    char sep;
    int state, fields, quoted, blank;
    field_t f;
    int count[NCOLS][NALIAS];       /* header: how often each accepted name appears */
    int at[NCOLS][NALIAS];          /* header: the field of its first appearance */
} reader_t;

static reader_t readers[3];
static field_t cells[NCOLS];
static FILE *in;
static int pushed[3], npushed;      /* bytes read ahead (the byte-order mark, CR LF) */
static int need, lo = 0x80, hi = 0xBF;  /* UTF-8: continuation bytes due, the next's range */

static int fail(const char *path, long lineno, const char *what)
{
    fflush(stdout);
    fprintf(stderr, "@P@: error: %s, line %ld: %s\n", path, lineno, what);
    return 2;
}

static int refused(const char *path, long lineno, int status)
{
    fflush(stdout);
    fprintf(stderr, "@P@: error: %s, line %ld: %s\n", path, lineno, @P@_error_message(status));
    return 3;
}

static int raw_byte(void)
{
    return npushed > 0 ? pushed[--npushed] : getc(in);
}

/* Drop a UTF-8 byte-order mark at the start of the input. */
static void skip_bom(void)
{
    int a = getc(in), b, c;
    if (a != 0xEF) {
        if (a != EOF) {
            pushed[npushed++] = a;
        }
        return;
    }
    b = getc(in);
    c = b == 0xBB ? getc(in) : EOF;
    if (b == 0xBB && c == 0xBF) {
        return;
    }
    if (c != EOF) {
        pushed[npushed++] = c;
    }
    if (b != EOF) {
        pushed[npushed++] = b;
    }
    pushed[npushed++] = a;
}

/* The next byte, checked as strict UTF-8 (no overlong form, no surrogate, nothing above
 * U+10FFFF, no sequence cut short); END_OF_INPUT or NOT_UTF8 otherwise. */
static int next_byte(void)
{
    int c = raw_byte();
    if (c == EOF) {
        return need ? NOT_UTF8 : END_OF_INPUT;
    }
    if (need) {
        if (c < lo || c > hi) {
            return NOT_UTF8;
        }
        --need;
        lo = 0x80;
        hi = 0xBF;
    } else if (c >= 0x80) {
        if (c >= 0xC2 && c <= 0xDF) {
            need = 1;
        } else if (c >= 0xE0 && c <= 0xEF) {
            need = 2;
            lo = c == 0xE0 ? 0xA0 : 0x80;
            hi = c == 0xED ? 0x9F : 0xBF;
        } else if (c >= 0xF0 && c <= 0xF4) {
            need = 3;
            lo = c == 0xF0 ? 0x90 : 0x80;
            hi = c == 0xF4 ? 0x8F : 0xBF;
        } else {
            return NOT_UTF8;
        }
    }
    return c;
}

/* Bytes of the white-space character that starts at s (Python's str.isspace: ASCII
 * \t \n \v \f \r, 0x1C-0x1F and space; U+0085, U+00A0, U+1680, U+2000-U+200A, U+2028,
 * U+2029, U+202F, U+205F, U+3000), 0 when none does. */
static size_t space_at(const unsigned char *s, size_t n)
{
    if (n >= 1 && ((s[0] >= 0x09 && s[0] <= 0x0D) || (s[0] >= 0x1C && s[0] <= 0x20))) {
        return 1;
    }
    if (n >= 2 && s[0] == 0xC2 && (s[1] == 0x85 || s[1] == 0xA0)) {
        return 2;
    }
    if (n >= 3 && ((s[0] == 0xE1 && s[1] == 0x9A && s[2] == 0x80)
                   || (s[0] == 0xE2 && s[1] == 0x80
                       && (s[2] <= 0x8A || s[2] == 0xA8 || s[2] == 0xA9 || s[2] == 0xAF))
                   || (s[0] == 0xE2 && s[1] == 0x81 && s[2] == 0x9F)
                   || (s[0] == 0xE3 && s[1] == 0x80 && s[2] == 0x80))) {
        return 3;
    }
    return 0;
}

/* The field without the white space around it (as Python's str.strip). */
static void trim(field_t *f)
{
    const unsigned char *s = (const unsigned char *)f->text;
    size_t start = 0, end = f->len, k, w;
    while (start < end && (w = space_at(s + start, end - start)) > 0) {
        start += w;
    }
    while (end > start) {
        for (w = 0, k = 1; k <= 3 && k <= end - start; ++k) {
            if (space_at(s + end - k, k) == k) {
                w = k;
                break;
            }
        }
        if (w == 0) {
            break;
        }
        end -= w;
    }
    memmove(f->text, f->text + start, end - start);
    f->len = end - start;
    f->text[f->len] = '\0';
}

static void keep(field_t *f, int c)
{
    if (c == 0) {
        f->nul = 1;
    }
    if (f->len < FIELD_MAX) {
        f->text[f->len++] = (char)c;
    } else {
        f->over = 1;
        if (!((c >= 0x09 && c <= 0x0D) || (c >= 0x1C && c <= 0x20))) {
            f->lost = 1;                                /* not white space: text was lost */
        }
    }
}

static void new_record(reader_t *r)
{
    r->state = START;
    r->fields = 0;
    r->quoted = 0;
    r->blank = 1;
    r->f.len = 0;
    r->f.over = r->f.lost = r->f.nul = 0;
}

/* A field ends: trimmed; in the header, counted against the accepted names; in a row, kept
 * in cells[] when cols[] reads it. */
static void end_field(reader_t *r, int header, const int cols[])
{
    int k, a;
    trim(&r->f);
    if (r->f.len > 0 || r->f.lost) {
        r->blank = 0;
    }
    for (k = 0; k < NCOLS; ++k) {
        if (header) {
            for (a = 0; a < NALIAS && ALIASES[k][a] != NULL; ++a) {
                if (!r->f.over && !r->f.nul && strcmp(r->f.text, ALIASES[k][a]) == 0
                    && r->count[k][a]++ == 0) {
                    r->at[k][a] = r->fields;
                }
            }
        } else if (cols[k] == r->fields) {
            cells[k] = r->f;
        }
    }
    ++r->fields;
    r->f.len = 0;
    r->f.over = r->f.lost = r->f.nul = 0;
}

/* One byte of a record that is not a line end outside quotes, for reader r (Python's csv:
 * a quote opens a quoted field only at its start, "" inside one is a quote, text after the
 * closing quote joins the field). */
static void feed(reader_t *r, int c, int header, const int cols[])
{
    switch (r->state) {
    case START:
        if (c == '"') {
            r->state = QUOTED;
            r->quoted = 1;
            return;
        }
        /* fall through */
    case PLAIN:
        if (c == r->sep) {
            end_field(r, header, cols);
            r->state = START;
        } else {
            keep(&r->f, c);
            r->state = PLAIN;
        }
        return;
    case QUOTED:
        if (c == '"') {
            r->state = QUOTE;
        } else {
            keep(&r->f, c);
        }
        return;
    default:                                            /* QUOTE: after a quote in quotes */
        if (c == '"') {
            keep(&r->f, c);
            r->state = QUOTED;
        } else if (c == r->sep) {
            end_field(r, header, cols);
            r->state = START;
        } else {
            keep(&r->f, c);
            r->state = PLAIN;
        }
    }
}

/* One record: the header (header != 0: one line, read by the three readers) or a row (read
 * by readers[use]). Returns 1, 0 at the end of the input, NOT_UTF8, or -2 for a read error. */
static int read_record(int header, int use, const int cols[])
{
    int c, i, first = header ? 0 : use, last = header ? 2 : use, any = 0;
    for (i = first; i <= last; ++i) {
        new_record(&readers[i]);
    }
    for (;;) {
        c = next_byte();
        if (c == NOT_UTF8) {
            return NOT_UTF8;
        }
        if (c == END_OF_INPUT) {
            if (ferror(in)) {
                return -2;
            }
            if (!any) {
                return 0;
            }
            break;
        }
        any = 1;
        if ((c == '\n' || c == '\r') && (header || readers[use].state != QUOTED)) {
            if (c == '\r') {
                int d = raw_byte();
                if (d != '\n' && d != EOF) {
                    pushed[npushed++] = d;
                }
            }
            break;
        }
        for (i = first; i <= last; ++i) {
            feed(&readers[i], c, header, cols);
        }
    }
    for (i = first; i <= last; ++i) {
        end_field(&readers[i], header, cols);
    }
    return 1;
}

/* The separator of the header: the one whose reader found the most fields (a comma on a tie
 * with it, a semicolon before a tab), a comma when none splits the line. */
static int choose_separator(void)
{
    int i, best = 0;
    for (i = 1; i < 3; ++i) {
        if (readers[i].fields > readers[best].fields) {
            best = i;
        }
    }
    return readers[best].fields > 1 ? best : 0;
}

/* cols[k]: the field of column k, from the header read by readers[use]; 0, or a message. */
static const char *pick_columns(int use, int cols[])
{
    static char why[FIELD_MAX + 160];
    const reader_t *r = &readers[use];
    int k, a, j, found, n;
    for (k = 0; k < NCOLS; ++k) {
        for (a = 0; a < NALIAS && ALIASES[k][a] != NULL; ++a) {
            if (r->count[k][a] > 1) {
                sprintf(why, "the column '%.200s' appears more than once; rename or drop the "
                        "copies", ALIASES[k][a]);
                return why;
            }
        }
    }
    for (k = 0; k < NCOLS; ++k) {
        cols[k] = -1;
        for (a = 0, found = 0; a < NALIAS && ALIASES[k][a] != NULL; ++a) {
            if (r->count[k][a] > 0) {
                if (found++) {
                    sprintf(why, "the columns '%.200s' and '%.200s' name the same signal; "
                            "keep one of them", ALIASES[k][0], ALIASES[k][a]);
                    return why;
                }
                cols[k] = r->at[k][a];
            }
        }
        if (cols[k] < 0) {
            n = sprintf(why, "missing %s column", k == 0 ? "time" : k <= @PU@_NU ? "input"
                                                                 : "output");
            for (a = 0; a < NALIAS && ALIASES[k][a] != NULL; ++a) {
                n += sprintf(why + n, "%s '%.200s'", a ? " or" : "", ALIASES[k][a]);
            }
            sprintf(why + n, " (a model file's [data] table is not read by the harness)");
            return why;
        }
        for (j = 0; j < k; ++j) {
            if (cols[j] == cols[k]) {
                sprintf(why, "one column is used for two signals ('%.200s' and '%.200s')",
                        ALIASES[j][0], ALIASES[k][0]);
                return why;
            }
        }
    }
    return 0;
}

/* A plain decimal number as Python's float reads it (sign, digits with a point, exponent;
 * inf, infinity, nan in any case): no hexadecimal, no nan(...), no digit separators. */
static int plain_number(const char *s, double *out)
{
    static const char *const WORDS[] = {"inf", "infinity", "nan"};
    const char *p = s + (*s == '+' || *s == '-');
    char *end;
    int digits = 0;
    size_t i, j;
    for (i = 0; i < 3; ++i) {
        for (j = 0; WORDS[i][j] != '\0' && (p[j] | 0x20) == WORDS[i][j]; ++j) {
        }
        if (WORDS[i][j] == '\0' && p[j] == '\0') {
            *out = strtod(s, &end);
            return *end == '\0';
        }
    }
    for (; *p >= '0' && *p <= '9'; ++p) {
        ++digits;
    }
    if (*p == '.') {
        for (++p; *p >= '0' && *p <= '9'; ++p) {
            ++digits;
        }
    }
    if (digits == 0) {
        return 0;
    }
    if (*p == 'e' || *p == 'E') {
        p += 1 + (p[1] == '+' || p[1] == '-');
        if (!(*p >= '0' && *p <= '9')) {
            return 0;
        }
        while (*p >= '0' && *p <= '9') {
            ++p;
        }
    }
    if (*p != '\0') {
        return 0;
    }
    *out = strtod(s, &end);
    return *end == '\0';
}

/* A cell: 1 and *out (NaN for a missing one; *mark ',' or '.' for the decimal mark it uses),
 * or 0 when it is not a number. */
static int read_cell(field_t *f, int sep, double *out, int *mark)
{
    char lower[8], *comma;
    size_t i;
    *mark = 0;
    if (f->nul || f->over) {
        return 0;
    }
    if (f->len < sizeof lower) {
        for (i = 0; i <= f->len; ++i) {
            char c = f->text[i];
            lower[i] = (char)(c >= 'A' && c <= 'Z' ? c - 'A' + 'a' : c);
        }
        for (i = 0; i < sizeof MISSING / sizeof MISSING[0]; ++i) {
            if (strcmp(lower, MISSING[i]) == 0) {
                *out = NAN;
                return 1;
            }
        }
    }
    comma = strchr(f->text, ',');
    if (sep != ',' && comma != NULL) {
        *mark = ',';
        if (strchr(comma + 1, ',') == NULL) {
            *comma = '.';
        }
    } else if (strchr(f->text, '.') != NULL) {
        *mark = '.';
    }
    return plain_number(f->text, out);
}

static void print_columns(void)
{
    size_t i;
    for (i = 0; i < sizeof COLUMNS / sizeof COLUMNS[0]; ++i) {
        printf(i ? ",%s" : "%s", COLUMNS[i]);
    }
    printf("\n");
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

/* The arguments: the data path and --theta0; 0, or the exit code of a usage error. */
static int arguments(int argc, char **argv, const char **path, real_t theta0[], int *have)
{
    int i, j;
    for (i = 1; i < argc; ++i) {
        if (strcmp(argv[i], "--theta0") == 0 && i + 1 < argc) {
            char *cursor = argv[++i];
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
            *have = 1;
        } else if (*path == NULL && (argv[i][0] != '-' || strcmp(argv[i], "-") == 0)) {
            *path = argv[i];
        } else {
            *path = NULL;
            break;
        }
    }
    if (*path == NULL) {
        fprintf(stderr, "usage: @P@ DATA.csv [--theta0 v1,v2,...]\n");
        return 2;
    }
    return 0;
}

int main(int argc, char **argv)
{
    const char *path = NULL, *why;
    real_t theta0[@PU@_NP], u[NUB], y[@PU@_NY], phi[@PU@_NK], u_prev[NUB], y_prev[@PU@_NY];
    int cols[NCOLS], have_theta0 = 0, i, nfields = 0, use = 0, status, rows = 0, mark;
    int printed = 0, header = 1;
    long lineno = 0, prev_line = 0, comma_line = 0, point_line = 0;
    double t = 0, t_prev = 0, value;
    char where[160];
    @P@_state state;
    status = arguments(argc, argv, &path, theta0, &have_theta0);
    if (status != 0) {
        return status;
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
    skip_bom();
    for (i = 0; i < NCOLS; ++i) {
        cols[i] = -1;
    }
    for (i = 0; i < 3; ++i) {
        readers[i].sep = SEPARATORS[i];
    }
    memset(u, 0, sizeof u);
    memset(y, 0, sizeof y);
    memset(u_prev, 0, sizeof u_prev);
    memset(y_prev, 0, sizeof y_prev);
    for (;;) {
        status = read_record(header, use, cols);
        ++lineno;
        if (status == NOT_UTF8) {
            return fail(path, lineno, "not UTF-8 text; save the file as UTF-8 (in Excel: "
                                      "'CSV UTF-8')");
        }
        if (status == -2) {
            return fail(path, lineno, "cannot read the file");
        }
        if (status == 0) {
            break;
        }
        if (header) {
            if (readers[0].fields == 1 && !readers[0].quoted && readers[0].blank) {
                continue;                               /* a blank line before the header */
            }
            use = choose_separator();
            why = pick_columns(use, cols);
            if (why != 0) {
                return fail(path, lineno, why);
            }
            nfields = readers[use].fields;
            header = 0;
            continue;
        }
        if (readers[use].blank) {
            continue;
        }
        if (readers[use].fields != nfields) {
            return fail(path, lineno, "the number of fields differs from the header's");
        }
        for (i = 0; i < NCOLS; ++i) {
            if (cells[i].over) {
                return fail(path, lineno, "a number is longer than FIELD_MAX = 1023 "
                                          "characters");
            }
            if (!read_cell(&cells[i], SEPARATORS[use], &value, &mark)) {
                return fail(path, lineno, i == 0 ? "t is not a number"
                                          : i <= @PU@_NU ? "an input is not a number"
                                          : "an output is not a number (NaN marks a missing "
                                            "one)");
            }
            comma_line = mark == ',' && !comma_line ? lineno : comma_line;
            point_line = mark == '.' && !point_line ? lineno : point_line;
            if (comma_line && point_line) {
                sprintf(where, "decimals are written with a comma on line %ld and with a "
                        "point on line %ld", comma_line, point_line);
                return fail(path, lineno, where);
            }
            if (i == 0) {
                t = value;
            } else if (i <= @PU@_NU) {
                u[i - 1] = (real_t)value;
            } else {
                y[i - 1 - @PU@_NU] = (real_t)value;
            }
            if (i <= @PU@_NU ? !isfinite(value) : isinf(value)) {
                return fail(path, lineno, i == 0 ? "t is not finite"
                                          : i <= @PU@_NU ? "an input is not finite"
                                          : "an output is infinite");
            }
        }
        /* the spacing to dt, relative to dt, allowing the rounding of t itself: a uniform
         * grid far from 0 (t = 8192 s at 1 kHz) has spacings off by an ulp of t */
        if (rows > 0 && !(fabs((t - t_prev) - DT) <= DT_RTOL * DT + 4 * DBL_EPSILON * fabs(t))) {
            return fail(path, lineno, "t is not spaced by the generated dt; resample the data "
                                      "or generate again with thetahat codegen --dt");
        }
#if @START@
        if (rows == 0) {
            @P@_start_from_y(&state, y);
        }
#endif
        if (rows > 0) {         /* the previous row's estimates, then the step to this row */
            status = @P@_phi_hat(&state, u_prev, y_prev, phi);
            if (status == @PU@_OK) {
                if (!printed++) {
                    print_columns();
                }
                print_row(t_prev, &state, phi);
                status = @P@_step(&state, u_prev, y_prev@NEXT@);
            }
            if (status != @PU@_OK) {
                return refused(path, prev_line, status);
            }
        }
        memcpy(u_prev, u, sizeof u);
        memcpy(y_prev, y, sizeof y);
        t_prev = t;
        prev_line = lineno;
        ++rows;
        if (ferror(stdout)) {
            return written();
        }
    }
    if (in != stdin) {
        fclose(in);
    }
    if (header) {
        return fail(path, lineno, "no header row (such as t,u,y)");
    }
    if (rows < 2) {
        return fail(path, lineno, rows ? "one data row; an estimate needs a record of at least "
                                         "two samples"
                                       : "a header but no data rows");
    }
    status = @P@_phi_hat(&state, u_prev, y_prev, phi);
    if (status != @PU@_OK) {
        return refused(path, prev_line, status);
    }
    print_row(t_prev, &state, phi);
    return written();
}
"""
