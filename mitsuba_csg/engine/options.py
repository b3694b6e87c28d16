"""Switches of the automaton's traversal mechanisms (`TraversalOptions`).

Every mechanism changes how much of the tree a ray walks, never what it finds: tests and
benchmarks turn them off one at a time and compare with the float64 reference.
"""
from __future__ import annotations

MIN_SET_SIZE = 4
# Fewest members of a hole set given a cell grid: a smaller set's 4-wide tree is two levels
# deep, as shallow as a cell's, and City-343k's 34,300 sets of 8 windows took 620 MB of cell
# trees and 12 s to build.
MIN_GRID_SIZE = 64


class TraversalOptions:
    """Switches of the automaton's traversal mechanisms (all on by default; tests and
    benchmarks turn them off one at a time).

    A plain class: Dr.Jit's symbolic control flow walks dataclasses it finds in loop state
    (the KernelTree) and would try to assign to a frozen one.
    """

    __slots__ = ("restart_at_sibling", "skip_to_sibling", "bounded_search", "near_first", "sets", "pass_through",
                 "min_set_size", "compounds", "neighbour_passes", "cell_passes", "min_grid_size")

    def __init__(self, restart_at_sibling: bool = True, skip_to_sibling: bool = True, bounded_search: bool = True,
                 near_first: bool = True, sets: bool = True, pass_through: bool = True, *,
                 min_set_size: int = MIN_SET_SIZE, compounds: bool = True, neighbour_passes: bool = True,
                 cell_passes: bool = True, min_grid_size: int = MIN_GRID_SIZE):
        self.restart_at_sibling = restart_at_sibling   # a loop restarts the looping child at its sibling's event
        self.skip_to_sibling = skip_to_sibling         # a fresh second child starts at the first child's event
                                                       # when that child fixes the node's state
        self.bounded_search = bounded_search           # otherwise the second child is searched only up to the
                                                       # first child's event (provisional results beyond)
        self.near_first = near_first                   # a fresh union / intersection search starts with the
                                                       # child whose box the ray enters first
        self.sets = sets                               # unions of leaves are searched as n-ary nodes
                                                       # (engine.set_walk)
        self.pass_through = pass_through               # an operation with a child the ray never meets
                                                       # after t_start is its other child, or a miss
        self.min_set_size = min_set_size               # fewest members of a union searched as a set
        self.compounds = compounds                     # set members may be small intersections and
                                                       # differences of convex leaves, not only leaves
        self.neighbour_passes = neighbour_passes       # a set walk inside at a member's exit searches
                                                       # that member's neighbours (engine.neighbours)
        self.cell_passes = cell_passes                 # a set walk that asks only the state at a point
                                                       # searches the members near its grid cell
        self.min_grid_size = min_grid_size             # fewest members of a set given a grid

    def __repr__(self) -> str:
        switches = ", ".join(f"{name}={getattr(self, name)}" for name in self.__slots__)
        return f"TraversalOptions({switches})"
