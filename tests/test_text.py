"""Numbers in warnings: a ratio to an exact fit's distance is not printed as meaningless digits."""

from o3dreg._text import LARGEST_FACTOR, ratio_text


def test_a_ratio_has_two_significant_digits_or_is_whole():
    assert ratio_text(8.66, 1.0) == "8.7"
    assert ratio_text(2.0, 1.0) == "2"
    assert ratio_text(1.25, 1.0) == "1.2"
    assert ratio_text(33.4, 1.0) == "33"


def test_a_ratio_to_an_exact_fit_is_over_the_largest_factor():
    # A mirror image that fits to rounding (1e-15 of the size) or exactly (0).
    assert ratio_text(0.5, 5e-15) == "over 1000"
    assert ratio_text(0.5, 0.0) == "over 1000"
    assert ratio_text(LARGEST_FACTOR, 1.0) == "over 1000"
    assert ratio_text(0.999 * LARGEST_FACTOR, 1.0) == "999"
