import os
import sys

os.environ.setdefault("MUJOCO_GL", "egl")
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def pytest_configure(config):
    # the fast tier for development: python -m pytest -q -m "not slow" tests/ (CI and the README run everything)
    config.addinivalue_line("markers", "slow: a subprocess run or a test that takes more than a few seconds")
