"""The timeline's playback: Play, Pause and the timer that steps through the EM iterations.

`Playback` owns the `Player` timer (`efem_viz.viewer.jobs`) and the Play button's label; each tick shows the next
step through the app's `set_step` (which draws it) and playback pauses at the last step. No viser import at run
time.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

from efem_viz.viewer.jobs import Player

if TYPE_CHECKING:
    from viser import GuiButtonHandle

    from efem_viz.viewer.session import ViewerSession


class Playback:
    """Play and pause the timeline of the session's result.

    Args:
        session: the viewer session (its state's step, step count, speed and `playing`; its lock).
        gui_play: the Play button (its label says Play or Pause).
        set_step: shows one EM step (`ViewerApp.set_step`).
    """

    def __init__(self, session: ViewerSession, gui_play: GuiButtonHandle, set_step: Callable[[int], None]) -> None:
        self.session = session
        self.gui_play = gui_play
        self.set_step = set_step
        self.player = Player(self.tick, lambda: self.session.state.speed)
        """The timer thread (steps per second: the state's `speed`)."""

    def play(self) -> None:
        """Start playback from the current step (from 0 when at the end)."""
        with self.session.lock:
            s = self.session.state
            if s.result is None or s.playing:
                return
            if s.step >= s.num_steps - 1:
                self.set_step(0)
            s.playing = True
            self.gui_play.label = "Pause"
            self.player.start()

    def pause(self) -> None:
        """Stop playback at the current step."""
        with self.session.lock:
            self.session.state.playing = False
            self.player.stop()
            self.gui_play.label = "Play"

    def toggle(self) -> None:
        """Pause when playing, else play."""
        if self.session.state.playing:
            self.pause()
        else:
            self.play()

    def tick(self) -> bool:
        """One playback step; False (and paused at the end) when playback is over."""
        with self.session.lock:
            s = self.session.state
            if not s.playing or s.result is None:
                return False
            if s.step + 1 >= s.num_steps:
                self.pause()
                return False
            self.set_step(s.step + 1)
            return True
