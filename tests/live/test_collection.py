"""Garbage collection held for the live paths (twin/live/collection.py): nothing is collected until asked, and
then what CPython's own thresholds say is due."""

import gc
import weakref

from twin.live.collection import collect_if_due, hold_collection, release_collection


class _Node:
    pass


def test_held_collection_runs_only_when_asked_and_then_finds_the_cycles():
    freed = []
    try:
        hold_collection()
        assert not gc.isenabled()
        assert collect_if_due() == -1  # nothing made since: nothing due
        for k in range(2 * gc.get_threshold()[0]):  # garbage cycles, more than a collection's threshold
            node = _Node()
            node.self = node
            weakref.finalize(node, freed.append, k)
        del node
        assert not freed  # the automatic collector is off
        assert collect_if_due() == 0  # the youngest generation was due
        assert len(freed) == 2 * gc.get_threshold()[0]
        assert collect_if_due() == -1
    finally:
        release_collection()
    assert gc.isenabled()
