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


ARGS_HEADERS = ["# The run", "# Algorithm 2", "# Dreamer (v1): the world model", "# Dreamer (v1): actor and value",
                "# Departures from the paper", "# Logging and run folders", "# Speed"]
MACHINERY = ["GraphedUpdate", "padded_pool", "set_speed_options", "check_args", "resolve_run", "open_run",
             "open_run_folder", "request_stop", "write_checkpoint", "read_checkpoint", "save_checkpoint",
             "load_checkpoint", "native_bf16", "UsageError", "parse_args", "disk_write", "check_memory",
             "first_update_fits"]


def test_each_script_reads_as_the_paper_then_its_machinery():
    """Args under its headers in the paper's order; CUDA graphs, checkpoints, locks, signals and argument checks in the
    last section only; no function over 50 lines."""
    import ast

    for script in ("rama_dreamer.py", "rama_metaworld.py"):
        parts = sections(script)
        args_block = parts[2][:parts[2].index("\ndef ")]
        headers = [line.strip() for line in args_block.splitlines() if line.strip().startswith("# ")]
        assert len(headers) == len(ARGS_HEADERS) and all(h.startswith(e) for h, e in zip(headers, ARGS_HEADERS)), \
            (script, headers)
        defined = {number: {node.name for node in ast.parse(text).body if hasattr(node, "name")}
                   for number, text in parts.items() if number > 1}
        for name in MACHINERY:
            assert name in defined[10] and not any(name in names for n, names in defined.items() if n < 10), name
        with open(os.path.join(ROOT, script)) as f:
            tree = ast.parse(f.read())
        long = [(node.name, node.end_lineno - node.lineno + 1) for node in ast.walk(tree)
                if isinstance(node, ast.FunctionDef) and node.end_lineno - node.lineno + 1 > 50]
        assert not long, (script, long)
