"""How a folder's walker episodes move: return, torso height and forward speed per tenth of the folder.

Reads the episode files of a run folder (or a results/ copy of one) in name order, per task folder, which is the order
they were collected, and prints one line per tenth: the mean return, the torso's mean height and the share of steps
above 1.2 (walker-stand rewards a torso above 1.2), and the mean forward speed. State vector only: dm_control's walker
observation is 14 orientations, the torso height (index 14) and 9 velocities, the second of them forward (index 16).

    python tools/posture.py results/walker_tables/prior_stand_paper_kl__dreamer__s1
"""
import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import rama_dreamer as rd  # noqa: E402  (where a run keeps its episodes, and a bad file as one line)

HEIGHT, FORWARD_SPEED = 14, 16  # indices into the walker's state vector (24 numbers)


def posture(files: list, parts: int = 10) -> list:
    """One dict per part of the files (fewer than `parts` files: one part): its episodes' indices, mean return, torso
    height, share of steps with the torso above 1.2 and forward speed. obs[0] is the reset's; the steps are obs[1:]."""
    rows = []
    for part in np.array_split(np.arange(len(files)), parts if len(files) >= parts else 1):
        episodes = [rd.read_npz(files[i], ["obs", "reward"]) for i in part]
        height = [e["obs"][1:, HEIGHT] for e in episodes]  # (T,) per episode
        speed = [e["obs"][1:, FORWARD_SPEED] for e in episodes]
        rows.append({"first": int(part[0]), "last": int(part[-1]),
                     "return": float(np.mean([e["reward"][1:].sum() for e in episodes])),
                     "height": float(np.mean([h.mean() for h in height])),
                     "above_1.2": float(np.mean([(h > 1.2).mean() for h in height])),
                     "speed": float(np.mean([v.mean() for v in speed]))})
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", help="a run folder, a results/ copy of one, or an episodes/ folder")
    parser.add_argument("--parts", type=int, default=10, help="how many parts to split the episodes into")
    args = parser.parse_args(argv)
    if args.parts < 1:
        sys.exit(f"error: --parts must be >= 1 (got {args.parts})")
    folders = rd.episode_folders(args.folder)  # one, or one per task of a --task-sequence run
    if not folders:
        sys.exit(f"error: {args.folder}: no episode files (*.npz) there")
    try:
        for folder in folders:
            files = rd.list_episode_files(folder)
            if rd.read_npz(files[0], ["obs"])["obs"].shape[-1] != 24:
                sys.exit(f"error: {folder}: not walker episodes from the state vector (24 numbers per observation)")
            if len(folders) > 1:
                print(folder)
            for row in posture(files, args.parts):
                print(f"episodes {row['first']:3d}-{row['last']:3d}: return {row['return']:6.1f}, torso height "
                      f"{row['height']:.2f} (above 1.2: {row['above_1.2']:.0%}), forward speed {row['speed']:.2f} m/s")
    except rd.UsageError as e:  # a truncated or foreign .npz
        sys.exit(f"error: {e}")


if __name__ == "__main__":
    main()
