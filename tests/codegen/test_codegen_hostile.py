"""Issue 37 (hostile round 3), codegen that cannot be injected (thetahat.codegen.c_text).

A model's title goes into the generated files' comments, its signal names into comments and
string literals, the name into every public identifier and file name. Each hostile text is
generated through ``thetahat codegen`` and compiled with the strictest flags
(``-std=c99 -Wall -Wextra -Werror -pedantic -Wtrigraphs``); the compiler's own lexer
(``cc -fpreprocessed -E``, which drops comments) shows that nothing left its comment. Each
hostile name is refused with an OptionError whose suggested name generates C that compiles.
The four files are written as one set: a full disk replaces none of them.
"""

from __future__ import annotations

import errno
import os
import re
import subprocess
from pathlib import Path

import pytest

from thetahat import errors as E
from thetahat.cli import main
from thetahat.codegen.harness import C_FLAGS
from thetahat.codegen.loader import find_compiler

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
STRICT = (*C_FLAGS, "-Wtrigraphs")
needs_cc = pytest.mark.skipif(find_compiler() is None, reason="no C compiler (cc or $CC)")


def model_file(folder: Path, title: str | None = None, stem: str = "prop1",
               base: str = "prop1") -> Path:
    """``examples/<base>.toml`` under ``folder/<stem>.toml``, with ``name = title``."""
    text = (EXAMPLES / f"{base}.toml").read_text()
    if title is not None:
        text = re.sub(r'^name = ".*"$', lambda m: f"name = {title}", text, count=1, flags=re.M)
    path = folder / f"{stem}.toml"
    path.write_text(text, encoding="utf-8")
    return path


def compile_strict(out: Path, name: str) -> None:
    """Build the harness with STRICT flags: no warning at all (stderr empty), exit 0."""
    cc = find_compiler()
    res = subprocess.run([cc, *STRICT, "-o", name, f"{name}_main.c", f"{name}.c", "-lm"],
                         cwd=out, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0 and not res.stderr.strip(), res.stderr


def code_without_comments(path: Path) -> str:
    """The file as the compiler sees it after removing comments (its own lexer)."""
    res = subprocess.run([find_compiler(), "-fpreprocessed", "-E", "-P", "-std=c99",
                          str(path)], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    return res.stdout


#: TOML spellings of hostile titles (the model file's ``name``).
TITLES = {
    "comment end and start": '"demo */ int thetahat_injected = 1; /*"',
    "trigraph backslash": '"ends in a trigraph ??/"',
    "every trigraph": '"??= ??( ??/ ??) ??\' ??< ??! ??> ??- ???/"',
    "trailing backslash": '"ends in a backslash \\\\"',
    "newline then code": '"line\\nint thetahat_injected = 1;\\n/*"',
    "carriage return": '"a\\rb */ int thetahat_injected = 1; /*"',
    "bidirectional override": '"safe \\u202e */ int thetahat_injected = 1; /* \\u202c"',
    "NUL and controls": '"a\\u0000b\\u0007c\\u001bd"',
    "comment markers glued": '"*//*/**/*/"',
    "Greek and accents": '"Moteur à courant continu, ω θ"',
    "line separator": '"a\\u2028*/ int thetahat_injected = 1; /*"',
}


@needs_cc
@pytest.mark.parametrize("title", TITLES.values(), ids=TITLES.keys())
def test_hostile_title_stays_in_its_comment(tmp_path, title, capsys):
    model = model_file(tmp_path, title)
    out = tmp_path / "c"
    assert main(["codegen", str(model), "--dt", "0.01", "-o", str(out)]) == 0, \
        capsys.readouterr().err
    compile_strict(out, "prop1")
    for name in ("prop1.h", "prop1.c", "prop1_main.c"):
        assert "thetahat_injected" not in code_without_comments(out / name)
        text = (out / name).read_text(encoding="utf-8")
        for ch in text:                      # no control or format character anywhere
            assert ch in "\n\t" or (ord(ch) >= 0x20 and ch not in "\u202e\u202c\u2028")
    if "ω" in title:                         # non-ASCII is kept in comments
        assert "Moteur à courant continu, ω θ" in (out / "prop1.h").read_text(encoding="utf-8")


#: Explicit names that are refused, with words of the reason.
NAMES = {
    "f": "f_advance",                       # the printer's helpers f_phi_hat, f_expm, ...
    "f_observer": "f_observer_",
    "law": "law_",
    "x": "X_HAT0",
    "u": "u_prev",
    "thetahat": "THETAHAT_",
    "real": "real_t",
    "read": "read_",
    "stream": "reserved for <string.h>",
    "memo": "reserved for <string.h>",
    "clean": "Makefile",
    "Makefile": "Makefile",
    "GNUmakefile": "Makefile",
    "int": "keyword",
    "bool": "keyword",
    "_Obs": "underscore",
    "_obs": "underscore",
    "a__b": "double underscore",
    "obs_": "double underscore",
    "9lives": "digit",
    "demo */ int x; /*": "ASCII letters, digits and underscores only",
    "ω": "ASCII letters",
    "": "empty",
    "obs" * 9: "more than 24",
}


@needs_cc
@pytest.mark.parametrize("name,words", NAMES.items(), ids=[repr(n) for n in NAMES])
def test_hostile_name_is_refused_with_a_name_that_works(tmp_path, capsys, name, words):
    model = model_file(tmp_path)
    out = tmp_path / "c"
    assert main(["codegen", str(model), "--dt", "0.01", "--name", name, "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert words in err and "internal error" not in err and "--name" in err, err
    assert not out.exists() or not any(out.iterdir())        # nothing written
    suggested = re.search(r"e\.g\. '([A-Za-z0-9_]+)'", err).group(1)
    assert main(["codegen", str(model), "--dt", "0.01", "--name", suggested,
                 "-o", str(out)]) == 0
    compile_strict(out, suggested)


def test_generate_c_refuses_the_name_as_an_option_error():
    from thetahat.codegen import generate_c
    from thetahat.models import lugre
    with pytest.raises(E.OptionError, match=r"f_advance.*choose another, e\.g\. 'f_obs'"):
        generate_c(lugre.observer(), dt=0.01, name="f")


@needs_cc
@pytest.mark.parametrize("stem,expected", [("two-mass spring", "two_mass_spring"),
                                            ("9", "obs_9"), ("Prop1", "prop1")])
def test_the_default_name_is_made_from_the_file_stem(tmp_path, stem, expected):
    from thetahat.modelfile import generate_c_from_model
    code = generate_c_from_model(model_file(tmp_path, stem=stem), dt=0.01)
    assert code.name == expected
    code.write(tmp_path / "c")
    compile_strict(tmp_path / "c", expected)


@pytest.mark.parametrize("stem,words", [("clean", "Makefile"), ("f", "f_advance"),
                                         ("stream", "reserved"), ("int", "keyword")])
def test_a_file_stem_that_cannot_name_c_asks_for_name(tmp_path, capsys, stem, words):
    model = model_file(tmp_path, stem=stem)
    assert main(["codegen", str(model), "--dt", "0.01", "-o", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert words in err and "--name" in err and "internal error" not in err, err


@needs_cc
def test_hostile_signal_names_from_the_api_are_escaped(tmp_path):
    """Names from SymPy symbols of any text (the API allows them; model files allow
    identifiers only) reach comments and string literals escaped: after the compiler's lexer
    drops the comments, the injected code is inside string literals only."""
    import sympy as sp

    from thetahat.codegen.c_text import comment_text, string_literal
    from thetahat.codegen.harness import harness_source
    bad = 'y */ int thetahat_injected; /* ??/ "q"'
    assert sp.Symbol(bad).name == bad                  # the API does allow such a name
    src = harness_source("obs", {"u": ["u"], "y": [bad], "x": ["x1"], "theta": ["a"]}, 1,
                         "double", False, 1e-3)
    assert comment_text(bad) in src and string_literal(bad) in src and "??" not in src
    (tmp_path / "obs_main.c").write_text(src)
    code = code_without_comments(tmp_path / "obs_main.c")
    outside_strings = re.sub(r'"(?:\\.|[^"\\\n])*"', '""', code)
    assert "thetahat_injected" in code and "thetahat_injected" not in outside_strings


# --- the four files, one set ------------------------------------------------------------------

def _previous(out: Path) -> dict[str, str]:
    out.mkdir(parents=True, exist_ok=True)
    old = {n: f"previous {n}\n" for n in ("prop1.h", "prop1.c", "prop1_main.c", "Makefile")}
    for n, text in old.items():
        (out / n).write_text(text)
    return old


@pytest.mark.parametrize("fail_at", [0, 2, 3])
def test_a_full_disk_replaces_none_of_the_four_files(tmp_path, capsys, monkeypatch, fail_at):
    """A write that fails (ENOSPC at the flush of file ``fail_at``): exit 2, the message says
    that nothing was replaced, and it is true; no temporary file is left."""
    model = model_file(tmp_path)
    out = tmp_path / "c"
    old = _previous(out)
    calls = []
    real_fsync = os.fsync

    def fsync(fd):
        calls.append(fd)
        if len(calls) == fail_at + 1:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_fsync(fd)
    monkeypatch.setattr(os, "fsync", fsync)
    assert main(["codegen", str(model), "--dt", "0.01", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "No space left on device" in err and "none of the 4 files was replaced" in err, err
    assert {p.name: p.read_text() for p in out.iterdir()} == old


def test_a_failed_rename_says_which_files_were_replaced(tmp_path, monkeypatch):
    from thetahat.modelfile import generate_c_from_model
    code = generate_c_from_model(model_file(tmp_path), dt=0.01)
    out = tmp_path / "c"
    old = _previous(out)
    real_replace = os.replace
    done = []

    def replace(src, dst):
        if len(done) == 2:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS))
        done.append(dst)
        return real_replace(src, dst)
    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(E.FileAccessError) as info:
        code.write(out)
    msg = str(info.value)
    files = code.files()
    names = list(files)
    for n in names[:2]:
        assert (out / n).read_text() == files[n] and str(out / n) in msg.split("replaced:")[1]
    for n in names[2:]:
        assert (out / n).read_text() == old[n]
        assert str(out / n) in msg.split("previous content kept:")[1]
    assert sorted(p.name for p in out.iterdir()) == sorted(names)
