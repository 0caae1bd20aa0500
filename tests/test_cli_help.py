"""Every command-line option's help states its default (issue: numbers that drift)."""

from __future__ import annotations

import argparse
import importlib

import pytest

CLIS = ["completion.bench", "completion.prior", "completion.data", "completion.train",
        "grasp.evaluate.cli", "grasp.evaluate.render", "grasp.cli", "grasp.evaluate.lift_training",
        "service.__main__", "service.load", "hands.barrett.urdf",
        "grasp.evaluate.sensor_parts"]
FLAGS = (argparse._StoreTrueAction, argparse._StoreFalseAction, argparse._StoreConstAction,
         argparse._HelpAction, argparse._VersionAction, argparse._SubParsersAction,
         argparse.BooleanOptionalAction)


class _Built(Exception):
    def __init__(self, parser: argparse.ArgumentParser) -> None:
        self.parser = parser


def _parsers(parser: argparse.ArgumentParser):
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from _parsers(sub)


@pytest.mark.parametrize("module", CLIS)
def test_every_option_says_its_default(module, monkeypatch):
    def capture(self, args=None, namespace=None):
        raise _Built(self)

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", capture)
    with pytest.raises(_Built) as built:
        importlib.import_module(module).main([])
    silent = []
    for parser in _parsers(built.value.parser):
        for action in parser._actions:
            if not action.option_strings or isinstance(action, FLAGS) or action.required:
                continue
            text = parser._get_formatter()._get_help_string(action) or ""
            if "default" not in text.lower() or "(default: %(default)s)" in text and (
                    action.default is None):  # "default: None" says nothing: say it in words
                silent.append(f"{parser.prog} {action.option_strings[0]}")
    assert not silent, f"options whose --help does not state the default: {silent}"
