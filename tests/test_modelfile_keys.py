"""The model file's keys as data (thetahat.modelfile.keys): the loader validates against the
tables, their defaults are the loader's, every shipped file's keys are in them."""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path

import numpy as np
import pytest

from thetahat.errors import ModelFileError
from thetahat.modelfile import EXAMPLE_MODEL, keys as K, loads_model, schema
from thetahat.modelfile.section import Section

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
#: The section tables by the name a file gives them (the three forms of Θ merged).
BY_SECTION: dict[str, set[str]] = {}
for _t in K.TABLES:
    BY_SECTION.setdefault(_t.section, set()).update(_t.names())


def test_the_tables_have_the_columns_and_known_types():
    assert K.COLUMNS == ("section", "key", "type", "default", "example", "description")
    for table in K.TABLES:
        names = table.names()
        assert len(set(names)) == len(names), table.section
        for row in table.rows():
            assert len(row) == len(K.COLUMNS) and row[0] == table.section
        for key in table.keys:
            assert key.type in K.TYPES and key.description.strip() and key.example.strip()
            assert bool(key.choices) == (key.type == "choice"), key.key
            if key.choices and key.literal:
                assert key.default in key.choices
    with pytest.raises(Exception, match="unknown type"):
        K.Table("x", (K.Key("k", "complex number", 1.0, "1.0", "?"),))


def test_every_example_is_a_toml_value_of_its_type():
    """Each example parses as TOML; the examples of numbers, booleans and choices pass the
    loader's own check of their type."""
    for table in K.TABLES:
        for key in table.keys:
            if key.type == "table":
                continue
            value = tomllib.loads(f"v = {key.example}")["v"]
            sec = Section("t.toml", table, {key.key: value})
            if key.type.endswith("number"):
                assert sec.number(key.key) == value
            elif key.type == "boolean":
                assert sec.boolean(key.key) is value
            elif key.type == "choice":
                assert sec.choice(key.key) == value


@pytest.mark.parametrize("path", sorted(EXAMPLES.glob("*.toml")), ids=lambda p: p.name)
def test_every_key_of_a_shipped_file_is_a_row(path):
    doc = tomllib.loads(path.read_text(encoding="utf-8"))
    assert set(doc) <= BY_SECTION["top level"]
    for section, value in doc.items():
        if isinstance(value, dict):
            assert set(value) <= BY_SECTION[section], section
            if section == "estimator" and "second" in value:
                assert set(value["second"]) <= BY_SECTION["estimator.second"]
    loads_model(path.read_text(encoding="utf-8"), source=str(path))      # and it loads


def test_the_literal_defaults_are_what_the_loader_uses():
    """EXAMPLE_MODEL gives no [scenario] and few [estimator] keys: every absent key with a
    literal default reads as its row says."""
    spec = loads_model(EXAMPLE_MODEL.replace("eps = 0.5\n", ""))
    sc, est, second = spec.scenario, spec.estimator, spec.estimator.second
    table_sc = K.SCENARIO
    assert (sc.t_end, sc.fs, sc.noise_std, sc.method, sc.rtol) == tuple(
        table_sc[k].default for k in ("t_end", "fs", "noise_std", "method", "rtol"))
    np.testing.assert_array_equal(sc.atol, table_sc["atol"].default)
    np.testing.assert_array_equal(sc.u_amplitudes[0], table_sc["u_amplitudes"].default)
    np.testing.assert_array_equal(sc.u_frequencies[0], table_sc["u_frequencies"].default)
    assert set(sc.defaults) == set(table_sc.names())
    assert ("auto" if est.eps_auto else est.eps, est.method, est.x_hat0_from_y,
            est.allow_nonminimum_phase) == tuple(
        K.ESTIMATOR[k].default for k in ("eps", "method", "x_hat0_from_y",
                                         "allow_nonminimum_phase"))
    assert (second.g_on_estimates, second.chain_poles) == (K.SECOND["g_on_estimates"].default,
                                                           None)


def test_the_loader_reads_its_defaults_and_keys_from_the_tables(monkeypatch):
    """Change a row, and the loader follows: the tables are the loader's data, not a copy."""
    rows = tuple(dataclasses.replace(k, default=7.0) if k.key == "t_end" else k
                 for k in K.SCENARIO.keys)
    monkeypatch.setattr(K, "SCENARIO", dataclasses.replace(K.SCENARIO, keys=rows))
    assert loads_model(EXAMPLE_MODEL).scenario.t_end == 7.0
    text = EXAMPLE_MODEL.replace("[estimator]\n", "[estimator]\nnote = 'x'\n")
    with pytest.raises(ModelFileError, match=r"\[estimator\]: unknown key\(s\) \['note'\]"):
        loads_model(text)
    extra = K.Key("note", "string", "", '"x"', "A note.")
    monkeypatch.setattr(K, "ESTIMATOR", dataclasses.replace(
        K.ESTIMATOR, keys=K.ESTIMATOR.keys + (extra,)))
    assert loads_model(text).estimator.eps == 0.5


def test_a_missing_required_key_says_what_is_expected():
    text = EXAMPLE_MODEL.replace('C = [[1.0, 0.0]]\n', "")
    with pytest.raises(ModelFileError, match=r"\[system\] C: missing; expected a r × n with "
                                             r"r = 1 outputs"):
        loads_model(text)
    with pytest.raises(ModelFileError, match=r"\[estimator\] law: missing; expected one of "
                                             r"\['gradient', 'least_squares'"):
        loads_model(EXAMPLE_MODEL.replace('law = "gradient"\n', ""))


ROOT = Path(__file__).resolve().parents[1]


def _model_file_hook():
    """docs/hooks/model_file.py, the hook that writes the reference page at each build."""
    import importlib.util
    path = ROOT / "docs" / "hooks" / "model_file.py"
    spec = importlib.util.spec_from_file_location("docs_model_file_hook", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _section_of(page: str, title: str) -> str:
    """The part of the page from the heading ``## title`` to the next ``## ``."""
    start = page.index(f"\n## {title}\n")
    end = page.find("\n## ", start + 1)
    return page[start:end if end > 0 else None]


def test_the_reference_page_is_every_row_of_the_tables():
    """docs/reference/model-file.md is generated from K.TABLES: under each section's heading,
    a row per key with its type, its default as the loader uses it and its example."""
    hook = _model_file_hook()
    page = hook.page()
    for table in K.TABLES:
        part = _section_of(page, "Top level" if table.section == "top level"
                           else f"`[{table.section}]`")
        if table.form:
            part = part[part.index(f"### {table.form[0].upper()}{table.form[1:]}\n"):]
        for key in table.keys:
            row = next((line for line in part.splitlines()
                        if line.startswith(f"| `{key.key}` |")), None)
            assert row is not None, (table.section, table.form, key.key)
            cells = [c.strip() for c in row.strip("|").split(" | ")]
            assert cells[1] == (key.type if not key.choices else
                                "one of " + ", ".join(f'`"{c}"`' for c in key.choices))
            if key.required:
                assert cells[2] == "**required**"
            elif key.literal:                                 # the loader's value, as TOML
                assert tomllib.loads(f"v = {cells[2].strip('`')}")["v"] == key.default
            assert cells[3] == f"`{key.example}`"
    for name in K.TYPES:
        assert f"\n| {name} | " in _section_of(page, "Types")


def test_the_reference_page_follows_the_tables(monkeypatch):
    """Change a row and the page changes: it is generated from the tables, not a copy."""
    hook = _model_file_hook()
    rows = tuple(dataclasses.replace(k, default=7.0) if k.key == "t_end" else k
                 for k in K.SCENARIO.keys)
    changed = tuple(dataclasses.replace(t, keys=rows) if t is K.SCENARIO else t
                    for t in K.TABLES)
    monkeypatch.setattr(K, "TABLES", changed)
    assert "| `t_end` | positive number | `7.0` |" in hook.page()
    monkeypatch.undo()
    assert "| `t_end` | positive number | `20.0` |" in hook.page()


def test_the_reference_page_is_in_the_site():
    """The nav lists the generated page, and the hook that writes it runs in the build."""
    config = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    assert _model_file_hook().PATH in config
    assert "docs/hooks/model_file.py" in config


def test_the_data_rows_are_the_keys_the_mapping_reads():
    """[data]'s inline tables are read by thetahat.io.mapping (below the model files): the
    keys it accepts, and the defaults it uses, are the rows of DATA_SIGNAL and DATA_RATE."""
    from thetahat.io.mapping import Signal, parse_data_table

    def refused(table):
        with pytest.raises(ModelFileError) as info:
            parse_data_table(table, ["u"], ["y"], ModelFileError)
        return str(info.value)

    signal = {k.key: tomllib.loads(f"v = {k.example}")["v"] for k in K.DATA_SIGNAL.keys}
    parsed = parse_data_table({"u": signal}, ["u"], ["y"], ModelFileError).u[0]
    assert parsed == Signal(**signal)
    assert str(list(K.DATA_SIGNAL.names())) in refused({"u": {**signal, "gain": 2.0}})
    bare = parse_data_table({"u": {"column": "a"}}, ["u"], ["y"], ModelFileError).u[0]
    assert (bare.scale, bare.offset) == (K.DATA_SIGNAL["scale"].default,
                                         K.DATA_SIGNAL["offset"].default)
    rate = {k.key: tomllib.loads(f"v = {k.example}")["v"] for k in K.DATA_RATE.keys}
    m = parse_data_table({"t": rate}, ["u"], ["y"], ModelFileError)
    assert (m.rate, m.start) == (rate["rate"], rate["start"])
    assert parse_data_table({"t": {"rate": 10.0}}, ["u"], ["y"],
                            ModelFileError).start == K.DATA_RATE["start"].default
    assert str(list(K.DATA_RATE.names())) in refused({"t": {**rate, "step": 0.1}})
    assert str(list(K.DATA.names())) in refused({"x": "a"})
