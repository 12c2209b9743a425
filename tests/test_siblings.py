"""rama_dreamer.py and rama_metaworld.py are siblings: the sections they share stay identical in text, so that
`diff rama_dreamer.py rama_metaworld.py` shows only the environment and task logic, and drift fails CI."""
import difflib
import os
import re

from helpers import ROOT

BANNER = re.compile(r"^# -{20,}\n# (\d+)\. .+\n# -{20,}\n", re.M)


def sections(script: str) -> dict:
    """{section number: text under its banner} of a script."""
    with open(os.path.join(ROOT, script)) as f:
        text = f.read()
    parts = BANNER.split(text)
    return {int(parts[i]): parts[i + 1] for i in range(1, len(parts), 2)}


def test_shared_sections_are_identical():
    dmc, metaworld = sections("rama_dreamer.py"), sections("rama_metaworld.py")
    assert sorted(dmc) == sorted(metaworld) == list(range(1, 10))
    # 4. storage and replay, 5. networks, 6. losses, 7. Algorithm 2, 8. acting, logging, checkpoints: word for word
    for number in (4, 5, 6, 7, 8):
        assert dmc[number] == metaworld[number], f"section {number} differs between the two scripts"
    # 9. the training loop: only Meta-World's expert collection (--collect-expert) is its own
    changed = [line for line in difflib.ndiff(dmc[9].splitlines(), metaworld[9].splitlines())
               if line[:2] in ("- ", "+ ")]
    assert all("collect_expert" in line for line in changed), changed
