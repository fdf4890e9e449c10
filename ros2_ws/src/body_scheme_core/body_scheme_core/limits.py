"""The sizes a learner takes: one place for the bounds that input checks, the configuration and saved states share.

Each is far beyond any use, and keeps one bad value (a parameter, a message, a state file) from allocating the
machine's memory or overflowing a count.
"""

from __future__ import annotations

__all__ = ["MAX_PARTS", "MAX_ACTIONS", "MAX_ACTION", "MAX_COORDINATE", "MAX_WINDOW", "MAX_NOISE", "MAX_INTEGER",
           "MAX_CHAIN_JOINTS"]

#: Most parts (markers) and actions (joints) of one learner: two arms and a torso with hands have about 40 of each.
MAX_PARTS = 100
MAX_ACTIONS = 100
#: Largest magnitude of an action (rad or m) taken without joint limits: no joint position is this large (a continuous
#: joint 1,500 turns away from zero), so a larger command is in other units or corrupt, and kernels would overflow.
MAX_ACTION = 1e4
#: Largest magnitude of a stored model's parameter or training output (an offset in m, a rotation in rad, a scale): a
#: km-sized link is corrupt, and the kinematics of larger ones overflow.
MAX_COORDINATE = 1e3
#: Longest test or training window (samples): beyond it the windows' memory and the GP's cost grow without use.
MAX_WINDOW = 10_000
#: Largest noise prior or fixed threshold, as a std (m or rad).
MAX_NOISE = 10.0
#: Largest count, step or id: a step a millisecond for 285,000 years, exact as a double, and a sum of a few of them
#: still fits an int64.
MAX_INTEGER = 2**53
#: Most joints in one chain local model (a 7-DOF arm with a torso lift and joints to spare).
MAX_CHAIN_JOINTS = 12
