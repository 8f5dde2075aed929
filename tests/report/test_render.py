"""The one HTML writer: templates travel as package data, escape what they are given and
refuse names their caller did not pass."""

import jinja2
import pytest

from mfdesign.report.render import cell, environment, render, write_html


def test_templates_are_package_data():
    names = set(environment().list_templates())
    assert {"base.html.j2", "_macros.html.j2", "sections.html.j2", "diagnosis.html.j2"} <= names


def test_every_page_escapes_and_carries_the_picture_check(tmp_path):
    page = write_html(
        tmp_path / "p.html",
        "sections.html.j2",
        title="<script>x</script>",
        written="now",
        summary=[],
        sections=[],
        root=tmp_path,
    ).read_text()
    assert "<title>&lt;script&gt;x&lt;/script&gt;</title>" in page and "<script>x" not in page
    assert "data-broken-images" in page and page.startswith("<!doctype html>")


def test_a_name_the_caller_did_not_pass_is_an_error():
    with pytest.raises(jinja2.UndefinedError, match="summary"):
        render("sections.html.j2", title="t", written="now", sections=[], root=".")


@pytest.mark.parametrize(
    "value, text",
    [
        (1.23456, "1.235"),
        (2.5e-7, "2.5e-07"),
        (3, "3"),
        (None, ""),
        ({"a": 0.5, "b": "x"}, "a = 0.5, b = x"),
        (["a", 1.0], "a, 1"),
    ],
)
def test_cells(value, text):
    assert cell(value) == text
