"""argparse types shared by the command lines (data, train, evaluate): clear errors at the edge,
and the --help formatter that states every default."""

from __future__ import annotations

import argparse
from collections.abc import Callable


class HelpWithDefaults(argparse.HelpFormatter):
    """--help that states each option's default: "(default: X)" after a help text that does not
    already say it in words (an option whose default is None must)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        # a flag (store_const, nargs 0) has the default of its dest, not one of its own
        skip = (action.default in (None, argparse.SUPPRESS) or isinstance(action.default, bool)
                or action.nargs == 0)
        if "default" in text.lower() or skip or not action.option_strings:
            return text
        return f"{text} (default: %(default)s)" if text else "default: %(default)s"


class DefaultsAndRawDescription(HelpWithDefaults, argparse.RawDescriptionHelpFormatter):
    """:class:`HelpWithDefaults` with the description as written."""


def name_list(choices: tuple[str, ...], what: str) -> Callable[[str], tuple[str, ...]]:
    """A comma list of names from ``choices``, or 'all'. Any case, and the tables' spelling too:
    "MVP", "Single-View" and "Camera Pan" mean mvp, single_view and camera_pan."""

    def parse(text: str) -> tuple[str, ...]:
        if text.strip().lower() == "all":
            return choices
        items = tuple(
            "_".join(x.strip().lower().replace("-", " ").split())
            for x in text.split(",")
            if x.strip()
        )
        bad = [x for x in items if x not in choices]
        if bad or not items:
            raise argparse.ArgumentTypeError(
                f"expected a comma-separated list of {what} from {', '.join(choices)} (or 'all'), "
                f"got {text!r}"
            )
        return tuple(dict.fromkeys(items))

    return parse


def integer_at_least(minimum: int) -> Callable[[str], int]:
    """An integer >= ``minimum``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {value}")
        return value

    return parse


def one_name(choices: tuple[str, ...], what: str) -> Callable[[str], str]:
    """One name from ``choices``, in any case and spelling as :func:`name_list` accepts."""
    many = name_list(choices, what)

    def parse(text: str) -> str:
        try:
            names = many(text) if text.strip().lower() != "all" else ()
        except argparse.ArgumentTypeError:
            names = ()
        if len(names) != 1:
            raise argparse.ArgumentTypeError(f"expected one of {', '.join(choices)}, got {text!r}")
        return names[0]

    return parse
