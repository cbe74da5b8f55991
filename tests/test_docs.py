"""The documentation that is generated from code matches the code, and its links lead somewhere."""

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


def _anchors(markdown: str) -> set[str]:
    """The anchors GitHub gives a file's headings: lower case, punctuation dropped, spaces to
    hyphens, and -1, -2, ... on repeats."""
    seen: dict[str, int] = {}
    anchors = set()
    for heading in re.findall(r"^#+ (.+)$", re.sub(r"```.*?```", "", markdown, flags=re.S), flags=re.M):
        slug = re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")
        anchors.add(slug if slug not in seen else f"{slug}-{seen[slug]}")
        seen[slug] = seen.get(slug, 0) + 1
    return anchors


def test_anchor_slugs_follow_github():
    assert _anchors("# A b\n## The real-time (delayed) setting\n## A b\n") == {
        "a-b", "the-real-time-delayed-setting", "a-b-1"}


def test_relative_links_and_their_anchors_resolve():
    root = DOCS.parent
    broken = []
    for page in [root / "README.md", root / "DEVELOPERS.md", *sorted(DOCS.glob("*.md"))]:
        text = page.read_text()
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if re.match(r"[a-z]+:", target):
                continue  # an absolute URL
            path, _, anchor = target.partition("#")
            file = (page.parent / path).resolve() if path else page
            if not file.exists():
                broken.append(f"{page.name}: {target} (no such file)")
            elif anchor and file.suffix == ".md" and anchor not in _anchors(file.read_text()):
                broken.append(f"{page.name}: {target} (no such heading)")
    assert not broken, broken


def test_recipe_paths_in_docs_and_benchmarks_exist():
    """Every `recipes/...toml` a page or benchmark names is a shipped recipe (a glob matches at least one)."""
    root = DOCS.parent
    pages = [root / "README.md", root / "DEVELOPERS.md", root / "Makefile", *sorted(DOCS.glob("*.md")),
             *sorted((root / "benchmarks").glob("*.py"))]
    missing = []
    for page in pages:
        for named in set(re.findall(r"recipes/[\w./*{},-]*?\.toml", page.read_text())):
            if not all(any(root.glob(path)) for path in _named_paths(f"`{named}`")):
                missing.append(f"{page.name}: {named}")
    assert not missing, missing
