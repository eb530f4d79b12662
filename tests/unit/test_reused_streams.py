"""Note [Reused streams]: a stream goes back once its holder is garbage, and the next holder on that device and
priority gets it; the others get streams of their own. Stand-in streams: the lending is the same on any machine."""

from __future__ import annotations

import gc

import torch

from vpengine.backends.streams import lend

CUDA0 = torch.device("cuda", 0)


class Holder:
    pass


def test_a_stream_goes_to_the_next_holder_once_its_holder_is_garbage():
    made: list[object] = []

    def new():
        made.append(object())
        return made[-1]

    first, second = Holder(), Holder()
    a = lend(first, CUDA0, priority=-7, new=new)
    b = lend(second, CUDA0, priority=-7, new=new)
    assert a is not b  # holders alive at once never share
    del first
    gc.collect()
    third = Holder()
    assert lend(third, CUDA0, priority=-7, new=new) is a
    assert lend(Holder(), CUDA0, priority=-6, new=new) not in (a, b)  # another priority: a stream of its own
    assert lend(Holder(), torch.device("cuda", 1), priority=-7, new=new) not in (a, b)  # another device too
    assert len(made) == 4
