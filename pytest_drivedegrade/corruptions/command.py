"""The command cells (spec 5, issue 40): the images and the ego status clean, the high-level command replaced.

- ``command_blind`` gives every frame the same command, ``STRAIGHT``. A planner of the three-command contract
  (RIGHT, LEFT, STRAIGHT in UniAD's order) has no value that means "no command"; what carries no information about
  a frame is a command that does not change from frame to frame, and of the three, ``STRAIGHT`` (follow the lane)
  is the one the data give away from junctions, so a frame that already had it gets its own command again. The
  cell measures how much the plan and its accuracy rest on the command. A command space other than the three is
  outside the planner contract (`planning.Planner`), so no other neutral value is defined.

Pure functions; the null control never comes here.
"""

from __future__ import annotations

from typing import TypeVar

from ..constants import COMMAND_BLIND

#: The command `command_blind` gives every frame: STRAIGHT in UniAD's order (`data.frame.Command`, a later stage
#: than the corruptions, so by its value; see the module's docstring for why this one).
NEUTRAL_COMMAND = 2
C = TypeVar("C", bound=int)


def command_for(command: C, family: str) -> C:
    """The command a cell of `family` gives a frame whose logged command is `command` (a `Command`), of its type."""
    return type(command)(NEUTRAL_COMMAND) if family == COMMAND_BLIND else command
