"""Importing the package does no network I/O: albumentations' update check is off by default."""

import subprocess
import sys


def _python(code: str) -> str:
    out = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout.strip()


def test_albumentations_update_check_off_by_default():
    code = (
        "import os; os.environ.pop('NO_ALBUMENTATIONS_UPDATE', None)\n"
        "import socket\n"
        "def refuse(*a, **k): raise AssertionError('network I/O on import')\n"
        "socket.socket.connect = refuse; socket.getaddrinfo = refuse\n"
        "import warnings; warnings.simplefilter('error')\n"
        "import lunarnav_ml.data.augment\n"
        "print(os.environ['NO_ALBUMENTATIONS_UPDATE'])\n"
    )
    assert _python(code) == "1"


def test_user_setting_is_kept():
    code = (
        "import os; os.environ['NO_ALBUMENTATIONS_UPDATE'] = '0'\n"
        "import lunarnav_ml\n"
        "print(os.environ['NO_ALBUMENTATIONS_UPDATE'])\n"
    )
    assert _python(code) == "0"
