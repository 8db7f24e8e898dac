"""The join's comparison of a turned motion's texture with the motion found's (`gscan.registration.join`), on the
tile counts measured over every view pair of rendered two-sided captures (bench/two_sided.py's objects)."""
from __future__ import annotations

from gscan.registration.colour import ColourAgreement
from gscan.registration.join import JoinParams, _texture_outweighs
from gscan.registration.pairwise import RegisterParams

RATIO = JoinParams().turn_texture_ratio
RP = RegisterParams()


def test_a_turn_a_partly_repeated_print_supports_is_outweighed():
    # Crayola: the right motion lines up in 58 of 67 tiles, the half turn in 25 of 74 (above a third: not refuted
    # on its own); the flat box: 19 of 23 against 124 of 469
    assert _texture_outweighs(ColourAgreement(67, 58), ColourAgreement(74, 25), RATIO, RP)
    assert _texture_outweighs(ColourAgreement(23, 19), ColourAgreement(469, 124), RATIO, RP)


def test_the_right_motion_is_never_outweighed_by_a_print_repeated_on_top_and_bottom():
    # the Pepsi pack: the wrong motion (top laid on bottom, both seen squarely) lines up in 374 of 411 tiles, the
    # right one (the sides, seen obliquely) in 42 of 67; Frozen Scrabble Jr's half turn, 171 of 288, against the
    # right motion's 103 of 111: neither motion outweighs the other
    assert not _texture_outweighs(ColourAgreement(411, 374), ColourAgreement(67, 42), RATIO, RP)
    assert not _texture_outweighs(ColourAgreement(111, 103), ColourAgreement(288, 171), RATIO, RP)


def test_too_few_textured_tiles_outweigh_nothing():
    few = RP.min_colour_tiles - 1
    assert not _texture_outweighs(ColourAgreement(few, few), ColourAgreement(100, 0), RATIO, RP)
    assert not _texture_outweighs(ColourAgreement(100, 100), ColourAgreement(few, 0), RATIO, RP)
