"""What a reader cannot read in a matplotlib figure: two texts drawn over each other (tick labels of
neighbouring panels, point names, a legend over a title) and a text cut by the box it is clipped to.
The saved PNG's tight bounding box already takes in every text, so a label cannot be cut at the canvas's
edge; these are the ways a label is still lost."""

from matplotlib.text import Text


def undrawn_tick_labels(fig) -> set[int]:
    """The ids of tick labels matplotlib keeps but does not draw: ticks outside their axis's view limits
    (a locator places one beyond each end)."""
    hidden = set()
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            low, high = sorted(axis.get_view_interval())
            span = (high - low) * 1e-9
            for tick in [*axis.get_major_ticks(), *axis.get_minor_ticks()]:
                if not low - span <= tick.get_loc() <= high + span:
                    hidden |= {id(tick.label1), id(tick.label2)}
    return hidden


def unreadable_texts(fig) -> list[str]:
    """Each pair of drawn texts whose boxes overlap, and each text reaching outside its clip box, after the
    figure's layout has run (`fig.canvas.draw()`)."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    hidden = undrawn_tick_labels(fig)
    shown = [
        (text, text.get_window_extent(renderer))
        for text in fig.findobj(Text)
        if text.get_visible() and text.get_text().strip() and id(text) not in hidden
    ]
    problems = []
    for i, (text, box) in enumerate(shown):
        problems += [
            f"{text.get_text()!r} over {other.get_text()!r}" for other, b in shown[i + 1 :] if box.overlaps(b)
        ]
        clip = text.get_clip_box() if text.get_clip_on() else None
        if clip is not None and (
            box.x0 < clip.x0 - 0.5
            or box.x1 > clip.x1 + 0.5
            or box.y0 < clip.y0 - 0.5
            or box.y1 > clip.y1 + 0.5
        ):
            problems.append(f"{text.get_text()!r} cut by its clip box")
    return problems
