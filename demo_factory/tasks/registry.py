"""Task names → task classes. Adding a task: one module and one line here."""

from __future__ import annotations

from demo_factory.tasks.base import Task
from demo_factory.tasks.close_drawer import CloseDrawer
from demo_factory.tasks.open_drawer import OpenDrawer
from demo_factory.tasks.open_wine_bottle import OpenWineBottle
from demo_factory.tasks.pick_and_lift import PickAndLift
from demo_factory.tasks.pick_up_cup import PickUpCup
from demo_factory.tasks.push_button import PushButton
from demo_factory.tasks.push_buttons import PushButtons
from demo_factory.tasks.put_knife_on_chopping_board import PutKnifeOnChoppingBoard
from demo_factory.tasks.put_money_in_safe import PutMoneyInSafe
from demo_factory.tasks.reach_and_drag import ReachAndDrag
from demo_factory.tasks.reach_target import ReachTarget
from demo_factory.tasks.slide_block_to_target import SlideBlockToTarget
from demo_factory.tasks.stack_blocks import StackBlocks
from demo_factory.tasks.stack_wine import StackWine
from demo_factory.tasks.take_money_out_safe import TakeMoneyOutSafe
from demo_factory.tasks.take_umbrella_out_of_umbrella_stand import TakeUmbrellaOutOfUmbrellaStand
from demo_factory.tasks.tower import Tower
from demo_factory.tasks.turn_oven_on import TurnOvenOn
from demo_factory.tasks.turn_tap import TurnTap
from demo_factory.tasks.wipe_desk import WipeDesk

# The multi-variation tasks come first: error messages list the accepted names in this order.
TASKS: dict[str, type[Task]] = {
    PushButtons.name: PushButtons,
    Tower.name: Tower,
    ReachTarget.name: ReachTarget,
    PushButton.name: PushButton,
    PickAndLift.name: PickAndLift,
    PickUpCup.name: PickUpCup,
    SlideBlockToTarget.name: SlideBlockToTarget,
    PutKnifeOnChoppingBoard.name: PutKnifeOnChoppingBoard,
    StackWine.name: StackWine,
    PutMoneyInSafe.name: PutMoneyInSafe,
    TakeMoneyOutSafe.name: TakeMoneyOutSafe,
    TakeUmbrellaOutOfUmbrellaStand.name: TakeUmbrellaOutOfUmbrellaStand,
    TurnTap.name: TurnTap,
    OpenDrawer.name: OpenDrawer,
    CloseDrawer.name: CloseDrawer,
    TurnOvenOn.name: TurnOvenOn,
    OpenWineBottle.name: OpenWineBottle,
    StackBlocks.name: StackBlocks,
    WipeDesk.name: WipeDesk,
    ReachAndDrag.name: ReachAndDrag,
}

# Tasks whose variations are ordered colour sequences with unseen test variations (HiveFormer's
# multi-variation tasks).
MULTI_VARIATION_TASKS: tuple[str, ...] = tuple(name for name, cls in TASKS.items() if cls.max_sequence > 1)
# Tasks whose instruction names one of several goals (a colour, a drawer, a shelf, a slot, ...): the ones
# human-written instructions are collected for (`demo-factory collect-instructions`).
INSTRUCTED_TASKS: tuple[str, ...] = tuple(name for name, cls in TASKS.items() if len(cls().variations) > 1)


def get_task(name: str) -> Task:
    """A fresh task instance; ``ValueError`` naming the accepted tasks for an unknown name."""
    try:
        return TASKS[name]()
    except KeyError:
        raise ValueError(f"unknown task {name!r}; accepted: {', '.join(TASKS)}") from None
