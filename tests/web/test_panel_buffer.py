"""The panel's stroke buffer (web/panel.py, `Panel.strokes_after`): what a feed is sent after its
cursor, read from the buffer's end, equals the whole buffer filtered, wherever the cursor is."""

from __future__ import annotations

from typing import Any

from hypothesis import given
from hypothesis import strategies as st

from usmswitch.web.panel import HISTORY_STROKES, Panel


class _Quiet:
    def listen(self, listener: Any) -> None:
        pass


def _stroke(cycle: int) -> dict[str, Any]:
    fields = ("operating_ns", "error_ns", "total_ns", "target_ns", "t_hat_ns", "flags")
    return {"cycle": cycle, "direction": "on", **dict.fromkeys(fields, cycle)}


@given(strokes=st.integers(0, HISTORY_STROKES + 300), cursor=st.integers(0, HISTORY_STROKES + 400))
def test_the_strokes_after_a_cursor_are_the_buffers_filtered(strokes: int, cursor: int) -> None:
    panel = Panel(_Quiet(), None, None)  # type: ignore[arg-type]
    for cycle in range(strokes):
        panel.on_note("stroke", _stroke(cycle))
    rows, gap = panel.strokes_after(cursor)
    kept = list(panel.strokes)
    first = kept[0][0] if kept else 0
    if kept and cursor < first - 1:
        assert (rows, gap) == ([row for _, row in kept], cursor > 0)
    else:
        assert (rows, gap) == ([row for seq, row in kept if seq > cursor], False)
