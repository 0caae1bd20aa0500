"""completion.cli: the argument types every command line shares."""

import argparse

import pytest

from completion.cli import integer_at_least, name_list, one_name

CHOICES = ("single_view", "mvp", "camera_pan")


def test_name_list_accepts_any_case_and_the_tables_spelling():
    parse = name_list(CHOICES, "rows")
    assert parse("MVP, Single-View") == ("mvp", "single_view")
    assert parse("Camera Pan,mvp,MVP") == ("camera_pan", "mvp")  # duplicates dropped, order kept
    assert parse("ALL") == CHOICES
    for bad in ("gpt", "", " , "):
        with pytest.raises(argparse.ArgumentTypeError, match="comma-separated list of rows"):
            parse(bad)


def test_one_name_wants_exactly_one():
    parse = one_name(CHOICES, "models")
    assert parse("Single-View") == "single_view"
    for bad in ("mvp,single_view", "all", "nope"):
        with pytest.raises(argparse.ArgumentTypeError, match="expected one of"):
            parse(bad)


def test_integer_at_least_says_what_was_expected():
    parse = integer_at_least(2)
    assert parse("3") == 3
    with pytest.raises(argparse.ArgumentTypeError, match="expected an integer, got 'x'"):
        parse("x")
    with pytest.raises(argparse.ArgumentTypeError, match="integer >= 2, got 1"):
        parse("1")
