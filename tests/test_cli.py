"""The ``shearfit`` command's surface: main(argv) without a subprocess."""

import pytest

from shearfit import __version__
from shearfit.app.cli import main


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert __version__ in capsys.readouterr().out


def test_no_command_prints_help(capsys):
    assert main([]) == 2
    assert "demo" in capsys.readouterr().out


def test_unknown_command_fails():
    with pytest.raises(SystemExit) as exc:
        main(["nope"])
    assert exc.value.code != 0


def test_demo_rejects_bad_count(capsys):
    assert main(["demo", "--n-galaxies", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--n-galaxies" in err
