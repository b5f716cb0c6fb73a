"""The per-view quality flag's rule (register/quality.py) on the numbers a registration produces."""

from __future__ import annotations

from geopose.register.quality import AGREEMENT_DEG, AGREEMENT_MM, DICE_OK, assess


def test_good_numbers_are_ok_even_with_the_silhouette_dice_of_a_good_pose():
    # validation phantoms 6010-6029: poses < 2 mm had silhouette Dice 0.75-0.89 (the old 0.85 cut called them doubtful)
    quality = assess(0.62, 0.76, 2.4, 3.0)
    assert quality.flag == "ok" and quality.reasons == ()


def test_a_silhouette_clearly_off_is_doubtful_and_far_off_failed():
    assert assess(0.62, DICE_OK - 0.05, 2.4, 3.0).flag == "doubtful"
    failed = assess(0.62, 0.5, 2.4, 3.0)
    assert failed.flag == "failed" and "silhouette Dice 0.50" in failed.reasons[0]


def test_stages_that_disagree_or_a_failed_check_make_it_doubtful():
    # validation: the TTO corrected the networks' estimate by up to 14 deg where the result was < 2 mm
    assert assess(0.62, 0.8, 14.0, 3.0).flag == "ok"
    turned = assess(0.62, 0.8, AGREEMENT_DEG + 1.5, 3.0)
    assert turned.flag == "doubtful" and f"turned the pose {AGREEMENT_DEG + 1.5:.1f} deg" in turned.reasons[0]
    assert assess(0.62, 0.8, 3.0, AGREEMENT_MM + 1.0).flag == "doubtful"
    assert assess(0.62, 0.8, 1.0, 3.0, doubts=("the two views place the patient 25 mm apart",)).flag == "doubtful"


def test_low_similarity_is_failed():
    assert assess(0.10, 0.8, 1.0, 3.0).flag == "failed"
    assert assess(0.30, 0.8, 1.0, 3.0).flag == "doubtful"
