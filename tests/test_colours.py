"""colours: one colour per detector in every figure (report and campaign plots)."""

from __future__ import annotations

from imufdi_cli import colours
from imufdi_cli.campaign import plots as campaign_plots


def test_detector_colours_are_fixed_and_distinct():
    known = list(colours.DETECTOR_COLOURS)
    assert len({colours.detector_colour(n) for n in known}) == len(known)
    assert colours.detector_colour("glt") == colours.detector_colour("glt")
    assert colours.detector_colour("a-new-one") in colours.PALETTE


def test_campaign_and_report_figures_share_the_table():
    for name in [*colours.DETECTOR_COLOURS, "a-new-one"]:
        assert campaign_plots.detector_colour(name) == colours.detector_colour(name)
