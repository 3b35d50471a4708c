"""The HiveFormer paper's nine task categories and the RLBench tasks it lists in each.

Written once, here, from the paper's supplement (Section 2, the 74 RLBench tasks by the challenge
they pose); the same grouping is in the co-authors' PolarNet code (`assets/74_tasks_per_category.json`).
A task may be in several categories: the supplement lists push buttons under planning and again
under rotation-invariant. Each task module declares its own ``categories``; a test holds every
declaration against these lists, so a tag cannot drift from the paper.
"""

from __future__ import annotations

PAPER_CATEGORIES: dict[str, tuple[str, ...]] = {
    "planning": ("basketball_in_hoop", "put_rubbish_in_bin", "meat_off_grill", "meat_on_grill", "change_channel",
                 "tv_on", "tower3", "push_buttons", "stack_wine"),
    "tools": ("slide_block_to_target", "reach_and_drag", "take_frame_off_hanger", "water_plants",
              "hang_frame_on_hanger", "scoop_with_spatula", "place_hanger_on_rack", "move_hanger", "sweep_to_dustpan",
              "take_plate_off_colored_dish_rack", "screw_nail"),
    "long term": ("wipe_desk", "stack_blocks", "take_shoes_out_of_box", "slide_cabinet_open_and_place_cups"),
    "rotation-invariant": ("reach_target", "push_button", "lamp_on", "lamp_off", "push_buttons", "pick_and_lift",
                           "take_lid_off_saucepan"),
    "motion planner": ("toilet_seat_down", "close_laptop_lid", "open_box", "open_drawer", "close_drawer", "close_box",
                       "phone_on_base", "toilet_seat_up", "put_books_on_bookshelf"),
    "multimodal": ("pick_up_cup", "turn_tap", "lift_numbered_block", "beat_the_buzz", "stack_cups"),
    "precision": ("take_usb_out_of_computer", "play_jenga", "insert_onto_square_peg",
                  "take_umbrella_out_of_umbrella_stand", "insert_usb_in_computer", "straighten_rope",
                  "pick_and_lift_small", "put_knife_on_chopping_board", "place_shape_in_shape_sorter",
                  "take_toilet_roll_off_stand", "put_umbrella_in_umbrella_stand", "setup_checkers"),
    "screw": ("turn_oven_on", "change_clock", "open_window", "open_wine_bottle"),
    "visual occlusion": ("close_microwave", "close_fridge", "close_grill", "open_grill", "unplug_charger",
                         "press_switch", "take_money_out_safe", "open_microwave", "put_money_in_safe", "open_door",
                         "close_door", "open_fridge", "open_oven", "plug_charger_in_power_supply"),
}

CATEGORIES: tuple[str, ...] = tuple(PAPER_CATEGORIES)


def paper_categories(paper_name: str) -> tuple[str, ...]:
    """The categories the paper lists an RLBench task under (empty for a task it does not evaluate)."""
    return tuple(category for category, names in PAPER_CATEGORIES.items() if paper_name in names)


def suite_name(category: str) -> str:
    """A category as a suite name: ``long term`` -> ``long_term``."""
    return category.replace(" ", "_").replace("-", "_")
