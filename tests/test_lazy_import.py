"""``import thetahat`` is lazy (PEP 562): it loads no subpackage, yet every public name works."""

from __future__ import annotations

import subprocess
import sys

import pytest

import thetahat


def test_import_loads_no_subpackage():
    """A fresh interpreter: after ``import thetahat`` the only thetahat modules are the package
    and the one line that holds its version."""
    code = ("import sys, thetahat; "
            "print(sorted(m for m in sys.modules if m.startswith('thetahat')))")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                         text=True).stdout.strip()
    assert out == "['thetahat', 'thetahat._version']"


@pytest.mark.parametrize("name", sorted(set(thetahat.__all__) - {"__version__"}))
def test_every_public_name_resolves_to_its_defining_module(name):
    value = getattr(thetahat, name)
    module = thetahat._MODULE_OF[name]
    assert value is getattr(sys.modules[f"thetahat.{module}"], name)
    assert name in dir(thetahat)


def test_unknown_name_is_an_attribute_error():
    """hasattr and ``from thetahat import X`` need exactly AttributeError."""
    assert not hasattr(thetahat, "no_such_name")
    with pytest.raises(ImportError, match="no_such_name"):
        exec("from thetahat import no_such_name", {})


def test_the_table_and_all_agree():
    assert set(thetahat._MODULE_OF) == set(thetahat.__all__) - {"__version__"}
