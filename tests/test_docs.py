"""The documentation that is generated from code matches the code."""

import re
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


def _named_paths(text: str) -> set[str]:
    """Paths in backticks, with `dir/{a,b}.toml` expanded to `dir/a.toml` and `dir/b.toml`."""
    named = set()
    for token in re.findall(r"`([^`]+\.toml)`", text):
        match = re.fullmatch(r"(.*)\{(.*)\}(.*)", token)
        named |= {f"{match[1]}{part}{match[3]}" for part in match[2].split(",")} if match else {token}
    return named


def test_recipe_list_names_every_shipped_recipe():
    """docs/recipes.md names each recipe; the dm_control row names its tasks (`dmc-<task>/`)."""
    text = (DOCS / "recipes.md").read_text()
    named = _named_paths(text)
    root = DOCS.parent / "recipes"
    missing = []
    for path in sorted(root.rglob("*.toml")):
        rel = path.relative_to(root).as_posix()
        task = path.parent.name.removeprefix("dmc-")
        dmc_row = path.parent.name.startswith("dmc-") and f"dmc-<task>/{path.name}" in named and task in text
        if rel not in named and not dmc_row:
            missing.append(rel)
    assert not missing, f"add to docs/recipes.md: {missing}"
