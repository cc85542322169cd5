import numpy as np

from train.figures import image_grid, normal_panel, normal_to_rgb


def test_normal_panel_marks_background_and_invalid_pixels():
    normal = np.zeros((2, 3, 3))
    normal[..., 2] = -1.0  # facing the camera: RGB (0.5, 0.5, 1)
    mask = np.array([[True, True, False], [True, False, False]])
    valid = np.array([[True, False, True], [True, True, True]])
    image = normal_panel(normal, mask, valid)
    assert np.allclose(image[0, 0], (0.5, 0.5, 1.0))
    assert np.allclose(image[0, 1], 0.0)  # invalid inside the mask: black
    assert np.allclose(image[~mask], 1.0)  # outside the mask: white, whatever its normal or validity
    assert np.allclose(normal_panel(normal, mask)[mask], normal_to_rgb(normal)[mask])


def test_image_grid_draws_colour_bars_only_where_labelled():
    images = [np.zeros((4, 4, 3)), np.arange(16.0).reshape(4, 4)]
    fig = image_grid(images, ["rgb", "values"], "title", "caption", colorbar_label=[None, "degrees"])
    labels = [ax.get_ylabel() for ax in fig.axes if ax.get_ylabel()]
    assert labels == ["degrees"] and len(fig.axes) == 3  # two panels and one bar


def test_image_grid_paints_flagged_pixels_and_marks_values_beyond_the_range():
    """Invalid pixels looked like valid ones in evaluate's error maps (their placeholder error in
    ordinary colours), and a fixed range clipped values without a sign on the colour bar."""
    from train.figures import FLAGGED_COLOUR

    values = np.arange(16.0).reshape(4, 4)
    flagged = np.zeros((4, 4), dtype=bool)
    flagged[0, :2] = True
    fig = image_grid([values, values], ["clipped", "within"], "title", "caption", colorbar_label="v",
                     limits=[(0.0, 10.0), (0.0, 20.0)], flagged=[flagged, None])
    panels = [ax for ax in fig.axes if ax.get_title()]
    overlay = panels[0].get_images()[-1].get_array()
    assert len(panels[0].get_images()) == 2 and len(panels[1].get_images()) == 1
    assert np.allclose(overlay[0, 0], (*FLAGGED_COLOUR, 1.0)) and overlay[1, 1, 3] == 0  # only flagged pixels are painted
    assert [panel.get_images()[0].colorbar.extend for panel in panels] == ["max", "neither"]


def test_pattern_chart_outlines_every_pattern():
    """A fully lit superpixel is white, like the gaps and the background: without an outline the
    learned sets' edges were lost."""
    from train.report_charts import chart_patterns

    fig = chart_patterns([("white", np.ones((2, 3, 4, 3), np.float32)), ("black", np.zeros((3, 3, 4, 3), np.float32))], "caption")
    assert [len(ax.patches) for ax in fig.axes] == [2, 3]


def test_evaluate_summary_names_the_gains_the_scenes_were_captured_at():
    from train.evaluate_command import _gains_text

    assert _gains_text({"scenes": [{"exposure": 0.0062}, {"exposure": 0.041}]}) == " (gain e = 0.0062..0.041)"
    assert _gains_text({"scenes": [{"exposure": 0.5}, {"exposure": 0.5}]}) == " (gain e = 0.5)"
    assert _gains_text({"scenes": []}) == ""
