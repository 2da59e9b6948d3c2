"""Every command-line option of jaxdrake's entry points (`python -m jaxdrake.lcm`, `python -m
jaxdrake.ros`) and of the example scripts says what it does in `--help`: each `add_argument`
call under jaxdrake/ and examples/ passes a non-empty `help=`."""

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def options_without_help():
    missing, seen = [], 0
    for path in sorted([*ROOT.glob("jaxdrake/**/*.py"), *ROOT.glob("examples/*.py")]):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "add_argument":
                seen += 1
                text = next((k.value for k in node.keywords if k.arg == "help"), None)
                if text is None or (isinstance(text, ast.Constant) and not str(text.value).strip()):
                    missing.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    return missing, seen


def test_every_command_line_option_has_help_text():
    missing, seen = options_without_help()
    assert seen > 20  # the two entry points' options and the examples' --out
    assert not missing, f"add_argument without help= at {missing}"


def test_the_entry_points_print_every_option_with_its_help(capsys, monkeypatch):
    import argparse

    from jaxdrake.lcm.__main__ import main as lcm_main
    from jaxdrake.ros.__main__ import main as ros_main

    parsers = []
    parse_args = argparse.ArgumentParser.parse_args
    monkeypatch.setattr(argparse.ArgumentParser, "parse_args",
                        lambda self, *args, **kwargs: parsers.append(self) or parse_args(self, *args, **kwargs))
    for main in (lcm_main, ros_main):
        with pytest.raises(SystemExit) as done:
            main(["--help"])
        assert done.value.code == 0
        printed = " ".join(capsys.readouterr().out.split())
        actions = parsers[-1]._actions
        assert len(actions) > 10
        for action in actions:
            assert action.help and " ".join(action.help.split()) in printed, action.dest
