"""Training relevance from the ground truth (`locretrieval.training.relevance`): positives and surely
unrelated negatives, scenes unrelated to each other, a negatives rule from outside the package."""

import dataclasses

import numpy as np
from training_runs import AT_25M, RELATIVE_POSE, negatives, train_config

from locretrieval import geometry
from locretrieval.config import validated
from locretrieval.frusta import TruncatedFrusta, pairwise_overlap_radii
from locretrieval.training.relevance import (
    NegativesRule,
    NotRelevantNegatives,
    TrainingRelevanceSettings,
    combined_pairs,
    training_pairs,
)


def test_relative_pose_training_pairs_against_a_direct_computation(scene):
    database = scene.database
    pairs = training_pairs(database, RELATIVE_POSE, AT_25M)
    position = geometry.position_errors(database.centers[:, None], database.centers[None])
    rotation = geometry.rotation_errors_deg(database.qvec[:, None], database.qvec[None])
    relevant = (position < 10.0) & (rotation < 30.0)
    np.fill_diagonal(relevant, False)
    graded = pairs.graded.toarray()
    np.testing.assert_array_equal(graded > 0, relevant)
    expected = 1 - (position / 10.0 + rotation / 30.0) / 2
    np.testing.assert_allclose(graded[relevant], expected[relevant], rtol=1e-6)
    frusta = TruncatedFrusta.of_images(database, np.arange(len(database)), 0.1, 25.0)
    overlap = pairwise_overlap_radii(frusta, frusta) > 0
    np.testing.assert_array_equal(pairs.related.toarray(), overlap | relevant)
    assert relevant.any() and (~overlap).any()  # both positives and surely unrelated pairs exist
    strict = training_pairs(database, negatives(NotRelevantNegatives()), AT_25M)
    np.testing.assert_array_equal(strict.related.toarray(), relevant)  # every pair not relevant may be a negative
    facing = training_pairs(database, negatives(max_rotation=90.0), AT_25M)
    np.testing.assert_array_equal(facing.related.toarray(), (overlap & (rotation <= 90.0)) | relevant)
    assert (overlap & (rotation > 90.0)).any()  # views facing each other share frustum volume: now negatives


def test_images_of_different_training_scenes_are_unrelated(scene):
    first, second = scene.database.subset(np.arange(12)), scene.database.subset(np.arange(12, 24))
    combined = combined_pairs([first, second], RELATIVE_POSE, [AT_25M, AT_25M])
    alone = [training_pairs(images, RELATIVE_POSE, AT_25M) for images in (first, second)]
    graded, related = combined.graded.toarray(), combined.related.toarray()
    np.testing.assert_array_equal(graded[:12, :12], alone[0].graded.toarray())
    np.testing.assert_array_equal(related[12:, 12:], alone[1].related.toarray())
    assert not graded[:12, 12:].any() and not related[:12, 12:].any() and not related[12:, :12].any()


@dataclasses.dataclass
class FarApart(NegativesRule):
    """A negatives rule from outside the package: negatives are the pairs more than ``metres`` apart."""

    metres: float

    def covisible(self, images, context):
        return lambda rows: geometry.pairwise_position_errors(images.centers[rows], images.centers) <= self.metres


def test_a_negatives_rule_from_outside_the_package_is_chosen_through_the_config(scene, tmp_path, monkeypatch):
    node = f"{{_target_: {__name__}.FarApart, metres: 15.0}}"
    cfg = train_config(tmp_path, "~train_relevance.negatives", f"+train_relevance.negatives={node}")
    settings = validated(TrainingRelevanceSettings, cfg.train_relevance, "train_relevance")
    database = scene.database
    pairs = training_pairs(database, settings, AT_25M)
    distance = geometry.position_errors(database.centers[:, None], database.centers[None])
    np.testing.assert_array_equal(pairs.related.toarray(), (distance <= 15.0) | (pairs.graded.toarray() > 0))
    assert (distance > 15.0).any()
    chosen = train_config(tmp_path, "train_relevance/negatives=not_relevant").train_relevance
    assert validated(TrainingRelevanceSettings, chosen, "train_relevance").negatives == NotRelevantNegatives()
