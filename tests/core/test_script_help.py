"""Every command's ``--help`` prints: argparse formats an argument's help with ``%`` (``%(default)s``), and a
description, epilog or usage that names ``%(prog)s``, so a bare ``%`` in one ("100 % crops") raises a TypeError when
the help is printed, not when the parser is built."""

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FOLDERS = ("src", "benchmarks", "research", "kernels", "refiner")
PROG_FORMATTED = {"description", "epilog", "usage"}  # formatted only when they name %(prog)
ESCAPED = re.compile(r"%%|%\(\w+\)[#0 +-]*\d*(?:\.\d+)?[diouxXeEfFgGcrsa]")


def _bare_percent(text: str) -> bool:
    return "%" in ESCAPED.sub("", text)


def _help_texts(path: Path):
    """(line, text) of each literal string argparse formats: an argument's help, a description, epilog or usage that
    names ``%(prog)`` (a text built at run time, an f-string or a call, is the code's to escape)."""
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Call):
            for kw in node.keywords:
                if not (isinstance(kw.value, ast.Constant) and isinstance(kw.value.value, str)):
                    continue
                if kw.arg == "help" or (kw.arg in PROG_FORMATTED and "%(prog)" in kw.value.value):
                    yield kw.value.lineno, kw.value.value


def _scripts():
    return sorted(p for folder in FOLDERS for p in (ROOT / folder).rglob("*.py") if "argparse" in p.read_text())


def test_the_scan_finds_the_commands():
    names = {p.name for p in _scripts()}
    assert {"bench_soft_maps.py", "bench_guard.py", "cli.py"} <= names


@pytest.mark.parametrize("text,bare", [("100 % crops", True), ("50%", True), ("100 %% crops", False),
                                       ("default %(default)s", False), ("%(default).2f %%", False),
                                       ("%%%", True)])
def test_a_bare_percent_is_found(text, bare):
    assert _bare_percent(text) == bare


def test_no_help_text_holds_a_bare_percent():
    found = [f"{p.relative_to(ROOT)}:{line}: {text!r}" for p in _scripts() for line, text in _help_texts(p)
             if _bare_percent(text)]
    assert not found, "argparse formats these with %: write %% for a percent sign\n" + "\n".join(found)
