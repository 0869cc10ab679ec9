"""Where the browser apps write when the user names no folder: the user's data folder, never the working
directory (run from a source checkout, as the README shows, a default of `./efem_out` put every export into the
checkout, where `git status` shows it).

* Linux and other Unix: `$XDG_DATA_HOME/efem-viz/` (default `~/.local/share/efem-viz/`);
* macOS: `~/Library/Application Support/efem-viz/`;
* Windows: `%LOCALAPPDATA%\\efem-viz\\`.

The apps print the folder at start.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

APP_DIR_NAME = "efem-viz"
"""Name of the apps' folder inside the user's data folder."""


def user_data_dir() -> Path:
    """The efem-viz folder in the user's data folder (not created here)."""
    if sys.platform == "win32":
        base = Path(os.environ.get("LOCALAPPDATA") or Path.home() / "AppData" / "Local")
    elif sys.platform == "darwin":
        base = Path.home() / "Library" / "Application Support"
    else:
        base = Path(os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share")
    return base.expanduser() / APP_DIR_NAME


def default_output_dir(app: str) -> Path:
    """The default output folder of one app (`user_data_dir() / app`), e.g. `~/.local/share/efem-viz/view`.

    Args:
        app: a short folder name for the app ("view").
    """
    return user_data_dir() / app
