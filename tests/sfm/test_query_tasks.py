"""The SfM paradigms' query tasks (`locretrieval.sfm.query_tasks`): one localisation per distinct set of images."""

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval.sfm.query_tasks import QueryTask, outcomes_per_image_set


def test_a_query_is_localised_once_per_distinct_set_of_top_k_images():
    calls = []

    def localize(images):
        calls.append(images)
        return f"{images}"

    task = QueryTask(0, top=((3, 1, 2), (2, 1, 3), (5,)), ks=((1, 3), (2, 3), (1, 3)))
    outcomes = outcomes_per_image_set(task, localize)
    assert outcomes == [["(3,)", "(1, 2, 3)"], ["(1, 2)", "(1, 2, 3)"], ["(5,)", "(5,)"]]
    assert calls == [(3,), (1, 2, 3), (1, 2), (5,)]
    calls.clear()
    task.known[(1, 2, 3)] = "cached"
    assert task.pending() == {(3,), (1, 2), (5,)} and not task.complete
    assert outcomes_per_image_set(task, localize)[0] == ["(3,)", "cached"]
    assert calls == [(3,), (1, 2), (5,)]
