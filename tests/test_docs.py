"""The docs hold together: every relative link and #anchor in README.md and docs/*.md resolves to a file and a heading
that exist, every image they show exists, and every deviation the scripts cite (`docs/deviations.md#<name>`) is a
heading of docs/deviations.md. The checkers are tested on small synthetic pages first, so that a broken link, anchor,
image or citation is shown to fail."""
import glob
import os
import re
from urllib.parse import unquote

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOCS = [os.path.join(ROOT, "README.md")] + sorted(glob.glob(os.path.join(ROOT, "docs", "*.md")))
SCRIPTS = [os.path.join(ROOT, name) for name in ("rama_dreamer.py", "rama_metaworld.py", "kitchen_env.py", "sweep.py",
                                                  "report.py")] + sorted(glob.glob(os.path.join(ROOT, "tools", "*.py")))
DEVIATIONS = os.path.join(ROOT, "docs", "deviations.md")
CITATION = re.compile(r"deviations\.md#([a-z0-9-]+)")  # how a script cites a deviation: docs/deviations.md#<name>
LINK = re.compile(r"(!?)\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
ANCHOR_TAG = re.compile(r"<a\s+(?:id|name)=\"([^\"]+)\"", re.IGNORECASE)


def prose_lines(text: str):
    """The lines outside fenced code blocks (``` or ~~~), with their line numbers."""
    fence = None
    for number, line in enumerate(text.splitlines(), 1):
        stripped = line.lstrip()
        if fence is None and stripped[:3] in ("```", "~~~"):
            fence = stripped[:3]
        elif fence is not None and stripped.startswith(fence):
            fence = None
        elif fence is None:
            yield number, line


def github_slug(heading: str) -> str:
    """A heading's anchor as GitHub makes it: the rendered text (inline code and link text kept, their markup gone),
    lowercased, every character but letters, digits, underscores, hyphens and spaces dropped, spaces to hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # [text](url) -> text
    text = re.sub(r"<[^>]+>", "", text.replace("`", ""))  # inline code's backticks, HTML tags
    text = re.sub(r"[^\w\- ]", "", text.strip().lower())
    return text.replace(" ", "-")


def anchors(text: str) -> set:
    """Every anchor a page offers: its headings' slugs (a repeated slug gets -1, -2, ... as on GitHub) and the
    explicit <a id="..."> / <a name="..."> tags."""
    found, seen = set(), {}
    for _, line in prose_lines(text):
        heading = re.match(r"\s{0,3}#{1,6}\s+(.*?)\s*#*\s*$", line)
        if heading:
            slug = github_slug(heading.group(1))
            found.add(slug if slug not in seen else f"{slug}-{seen[slug]}")
            seen[slug] = seen.get(slug, 0) + 1
        found.update(ANCHOR_TAG.findall(line))
    return found


def links(text: str):
    """(line number, target, is an image) of every inline link and image outside code (fenced blocks, code spans)."""
    for number, line in prose_lines(text):
        for image, target in LINK.findall(re.sub(r"`[^`]*`", "", line)):
            yield number, target, bool(image)


def check_page(path: str, text: str = None) -> list:
    """One line per broken relative link, missing image or missing #anchor of a Markdown page (`text`: the page's
    contents, read from `path` when not given; relative targets resolve from the page's folder)."""
    text = open(path, encoding="utf-8").read() if text is None else text
    errors, pages = [], {}
    for number, target, image in links(text):
        if re.match(r"[a-z][a-z0-9+.-]*:", target, re.IGNORECASE):  # https:, mailto:: not checked here
            continue
        file_part, _, anchor = target.partition("#")
        where = f"{os.path.relpath(path, ROOT)}:{number}: {target}"
        linked = os.path.normpath(os.path.join(os.path.dirname(path), unquote(file_part))) if file_part else path
        if file_part and not os.path.exists(linked):  # an #anchor alone points into the page itself
            errors.append(f"{where}: {'missing image' if image else 'broken link'} (no {os.path.relpath(linked, ROOT)})")
            continue
        if anchor:
            if not linked.endswith(".md"):
                errors.append(f"{where}: an anchor into a file that is not Markdown")
                continue
            if linked not in pages:
                pages[linked] = anchors(text if linked == path else open(linked, encoding="utf-8").read())
            if unquote(anchor) not in pages[linked]:
                errors.append(f"{where}: broken anchor (no heading #{anchor} in {os.path.relpath(linked, ROOT)})")
    return errors


def check_citations(sources: dict, deviations_text: str) -> list:
    """One line per deviation name cited (`deviations.md#<name>`) in `sources` ({path: text}) that is no anchor of
    the deviations page."""
    known = anchors(deviations_text)
    return [f"{os.path.relpath(path, ROOT)}:{text.count(chr(10), 0, m.start()) + 1}: deviations.md#{m.group(1)}: no such "
            f"deviation in docs/deviations.md" for path, text in sources.items() for m in CITATION.finditer(text)
            if m.group(1) not in known]


# The checkers, on synthetic pages: each kind of breakage is caught, and what is fine passes.
def test_github_slugs_as_github_makes_them():
    assert github_slug("Methods (`--method`)") == "methods---method"
    assert github_slug("Walker Table 1: same task (walk's M)") == "walker-table-1-same-task-walks-m"
    assert github_slug("Run folders and `--resume`") == "run-folders-and---resume"
    assert github_slug("Reproducing Tables 1–3") == "reproducing-tables-13"
    assert github_slug("state-observations") == "state-observations"
    assert github_slug("[a link](x.md) in a heading") == "a-link-in-a-heading"
    page = "# Title\n## Twice\n## Twice\n```\n## not a heading\n```\n<a id=\"kept\"></a>\n"
    assert anchors(page) == {"title", "twice", "twice-1", "kept"}


def test_a_broken_link_a_broken_anchor_and_a_missing_image_each_fail(tmp_path):
    (tmp_path / "other.md").write_text("# Other page\n## A section\n")
    (tmp_path / "figure.png").write_bytes(b"\x89PNG")
    page = tmp_path / "page.md"
    good = ("# Page\n[ok](other.md) [ok](other.md#a-section) [ok](#page) ![ok](figure.png) [web](https://x.org/#y)\n"
            "`[in code](nowhere.md)`\n```\n[in a block](nowhere.md)\n```\n")
    assert check_page(str(page), good) == []
    bad = {"[broken](missing.md)": "broken link", "[anchor](other.md#no-such-section)": "broken anchor",
           "[here](#nowhere)": "broken anchor", "![figure](missing.png)": "missing image",
           "[dir](figure.png#x)": "not Markdown"}
    for line, error in bad.items():
        errors = check_page(str(page), good + line + "\n")
        assert len(errors) == 1 and error in errors[0] and "page.md:" in errors[0], (line, errors)


def test_an_unknown_deviation_name_fails():
    deviations = "# Deviations\n### state-observations\n### Adam eps\n"
    cited = {os.path.join(ROOT, "a.py"): "x = 1  # docs/deviations.md#state-observations, deviations.md#adam-eps\n"}
    assert check_citations(cited, deviations) == []
    cited[os.path.join(ROOT, "b.py")] = "\n# see docs/deviations.md#no-such-name\n"
    errors = check_citations(cited, deviations)
    assert len(errors) == 1 and "b.py:2: deviations.md#no-such-name" in errors[0]


# The repository's own docs and scripts.
@pytest.mark.parametrize("path", DOCS, ids=[os.path.relpath(p, ROOT) for p in DOCS])
def test_every_link_anchor_and_image_of_the_docs_resolves(path):
    assert check_page(path) == []


def test_every_deviation_the_scripts_cite_is_a_heading_of_the_deviations_page():
    sources = {path: open(path, encoding="utf-8").read() for path in SCRIPTS if os.path.exists(path)}
    assert check_citations(sources, open(DEVIATIONS, encoding="utf-8").read()) == []


def test_the_deviations_page_names_its_entries_once():
    """Stable names: each deviation heading is kebab-case and unique, so its anchor is the name itself."""
    names = [m.group(1) for _, line in prose_lines(open(DEVIATIONS, encoding="utf-8").read())
             for m in [re.match(r"### (.+)$", line)] if m]
    assert names and all(re.fullmatch(r"[a-z0-9]+(-[a-z0-9]+)*", n) for n in names), names
    assert len(names) == len(set(names))
