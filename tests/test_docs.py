"""The documentation that is generated from code matches the code."""

from pathlib import Path

from layered.reference import reference

DOCS = Path(__file__).parent.parent / "docs"


def test_recipe_reference_is_generated_from_the_schema():
    committed = (DOCS / "recipe-reference.md").read_text()
    assert committed == reference(), "regenerate with: python -m layered.reference > docs/recipe-reference.md"


def test_reference_lists_every_recipe_key():
    text = reference()
    for key in ("`period`", "`sees`", "`eval_threshold`", "`order`", "`policy_delay`", "`seed_offset`"):
        assert key in text
