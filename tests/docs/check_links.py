#!/usr/bin/env python3
"""Checks that every relative link in README.md, CHANGELOG.md and docs/**/*.md resolves.

A link resolves when the file or directory it names exists (relative to the page that links) and, for a link
with a #fragment into a Markdown file (or a bare #fragment into the page itself), when that file has a heading
whose GitHub slug is the fragment. Links with a scheme (https:, mailto:) are not followed. Standard library only.

    python3 tests/docs/check_links.py [REPOSITORY_ROOT]     # exit 0 when every link resolves, 1 otherwise
"""
import pathlib
import re
import sys
import urllib.parse

# Inline links and images: [text](target) or ![alt](target "title"); the text may span lines.
INLINE_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(\s*<?([^)\s>]*)>?(?:\s+\"[^\"]*\")?\s*\)")
# Reference definitions: [label]: target
REFERENCE = re.compile(r"^ {0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s|$)", re.MULTILINE)
HEADING = re.compile(r"^ {0,3}(#{1,6})\s+(.*?)\s*#*\s*$")
FENCE = re.compile(r"^ {0,3}(`{3,}|~{3,})")
HTML_ANCHOR = re.compile(r"<a\s+(?:name|id)=\"([^\"]+)\"", re.IGNORECASE)


def strip_code(text):
    """The text with fenced code blocks and inline code spans blanked (links inside code are not links)."""
    lines, fence = [], None
    for line in text.split("\n"):
        match = FENCE.match(line)
        if fence:
            if match and match.group(1)[0] == fence[0] and len(match.group(1)) >= len(fence):
                fence = None
            lines.append("")
            continue
        if match:
            fence = match.group(1)
            lines.append("")
            continue
        lines.append(line)
    text = "\n".join(lines)
    return re.sub(r"(`+)(?:(?!\1).)+?\1", lambda m: " " * len(m.group(0)), text, flags=re.DOTALL)


def slug(heading):
    """GitHub's anchor for a heading: lower case, markup and punctuation dropped, spaces to hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link in a heading keeps its text
    text = re.sub(r"<[^>]+>", "", text)  # inline HTML
    text = text.strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)  # keeps letters, digits, underscores, hyphens and spaces
    return text.replace(" ", "-")


def anchors(path, cache={}):
    """Every anchor a Markdown file offers: its headings' slugs (repeats get -1, -2, ...) and HTML anchors."""
    if path not in cache:
        found, seen, fence = set(), {}, None
        text = path.read_text(encoding="utf-8")
        for line in text.split("\n"):
            match = FENCE.match(line)
            if fence:
                if match and match.group(1)[0] == fence[0] and len(match.group(1)) >= len(fence):
                    fence = None
                continue
            if match:
                fence = match.group(1)
                continue
            heading = HEADING.match(line)
            if heading:
                base = slug(heading.group(2))
                count = seen.get(base, 0)
                seen[base] = count + 1
                found.add(base if count == 0 else f"{base}-{count}")
        found.update(HTML_ANCHOR.findall(text))
        cache[path] = found
    return cache[path]


def check_page(page, root):
    """The broken links of one page, as messages naming the page, the line and the link."""
    text = page.read_text(encoding="utf-8")
    code_free = strip_code(text)
    targets = [(m.start(), m.group(1)) for m in INLINE_LINK.finditer(code_free)]
    targets += [(m.start(), m.group(1)) for m in REFERENCE.finditer(code_free)]
    problems = []
    for offset, target in sorted(targets):
        if not target or re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target):
            continue  # empty, or absolute (https:, mailto:, ...)
        line = code_free.count("\n", 0, offset) + 1
        where = f"{page.relative_to(root)}:{line}: link '{target}'"
        path_part, _, fragment = target.partition("#")
        path_part = urllib.parse.unquote(path_part)
        if path_part.startswith("/"):
            problems.append(f"{where}: an absolute path; links must be relative")
            continue
        linked = (page.parent / path_part).resolve() if path_part else page.resolve()
        if not linked.exists():
            problems.append(f"{where}: {linked.relative_to(root.resolve()) if linked.is_relative_to(root.resolve()) else linked} does not exist")
            continue
        if not linked.is_relative_to(root.resolve()):
            problems.append(f"{where}: points outside the repository")
            continue
        if fragment:
            if linked.is_dir() or linked.suffix.lower() != ".md":
                problems.append(f"{where}: an anchor into a file that is not Markdown")
            elif urllib.parse.unquote(fragment).lower() not in anchors(linked):
                problems.append(f"{where}: {linked.relative_to(root.resolve())} has no heading '#{fragment}'")
    return problems


def pages(root):
    found = [root / "README.md", root / "CHANGELOG.md"]
    found += sorted((root / "docs").rglob("*.md"))
    return found


def main():
    root = pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else pathlib.Path(__file__).resolve().parents[2])
    problems = []
    for page in pages(root):
        if not page.exists():
            problems.append(f"{page.relative_to(root)}: missing")
            continue
        problems += check_page(page, root)
    for problem in problems:
        print(problem)
    checked = [p for p in pages(root) if p.exists()]
    print(f"check_links: {len(checked)} pages, {len(problems)} broken link(s)")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
