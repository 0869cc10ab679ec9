"""The `?` keyboard cheat sheet: one modal overlay per client, opened and closed by the same key.

No viser import: the clients are viser `ClientHandle`s, used through `client.gui` and `client.client_id`.
"""

from __future__ import annotations

import threading
from typing import Any, Iterable, Sequence

from annotator.tools import Tool, cheat_sheet_markdown


class CheatSheets:
    """The open cheat-sheet overlays, by client id (under a lock: keys and buttons run on viser's worker threads).

    Args:
        tools: the tool table the sheet lists.
    """

    def __init__(self, tools: Sequence[Tool]) -> None:
        self.tools = tuple(tools)
        self.open: dict[int, Any] = {}
        """Client id → its open modal."""
        self._lock = threading.Lock()

    def toggle(self, clients: Iterable[Any]) -> bool:
        """Open the sheet over each client's view, or close it where open; True when one was opened."""
        opened = False
        for c in clients:
            with self._lock:
                modal = self.open.pop(c.client_id, None)
                if modal is not None:
                    modal.close()
                    continue
                modal = c.gui.add_modal("Keyboard shortcuts")
                with modal:
                    c.gui.add_markdown(cheat_sheet_markdown(self.tools))
                    close = c.gui.add_button("Close (?)")
                self.open[c.client_id] = modal

            def on_close(_event: Any, c: Any = c, modal: Any = modal) -> None:
                with self._lock:
                    if self.open.get(c.client_id) is modal:
                        del self.open[c.client_id]
                        modal.close()

            close.on_click(on_close)
            opened = True
        return opened

    def forget(self, client_id: int) -> None:
        """A client left: drop its overlay."""
        with self._lock:
            self.open.pop(client_id, None)
