"""rama_dreamer.py and rama_metaworld.py are siblings: the sections they share stay identical in text, so that
`diff rama_dreamer.py rama_metaworld.py` shows only the environment and task logic, and drift fails CI."""
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
    assert sorted(dmc) == sorted(metaworld) == list(range(1, 11))
    # 4. storage and replay, 5. networks, 6. Dreamer's losses, 7. Algorithm 2, 8. acting and logging, 9. the training
    # loop, 10. speed and reliability: word for word (each script's expert collection and its own flag checks,
    # check_env_args, live in its section 3)
    for number in range(4, 11):
        assert dmc[number] == metaworld[number], f"section {number} differs between the two scripts"
