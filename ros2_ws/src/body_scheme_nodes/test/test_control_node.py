"""control_node's settings of exploring near an unsure answer (ExploreSettings)."""

import pytest

from body_scheme_core.errors import InvalidInputError
from body_scheme_nodes.control_node import ExploreSettings


def test_the_defaults_are_accepted():
    settings = ExploreSettings(False, 5, 0.1, 60.0)
    assert (settings.enabled, settings.samples, settings.radius, settings.timeout) == (False, 5, 0.1, 60.0)


@pytest.mark.parametrize("args, match", [
    (("yes", 5, 0.1, 60.0), "explore_when_unsure"), ((True, 0, 0.1, 60.0), "explore_samples.*: n_samples"),
    ((True, True, 0.1, 60.0), "explore_samples.*: n_samples"),
    ((True, 1001, 0.1, 60.0), "explore_samples.*: n_samples"),
    ((True, 5, 0.0, 60.0), "explore_radius: radius"), ((True, 5, 1.5, 60.0), "explore_radius: radius"),
    ((True, 5, 0.1, 0.0), "explore_timeout"),
    ((True, 5, 0.1, float("inf")), "explore_timeout")])
def test_bad_values_are_refused_with_the_parameter_named(args, match):
    with pytest.raises(InvalidInputError, match=match):
        ExploreSettings(*args)
