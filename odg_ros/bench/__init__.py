"""``odg bench`` and ``odg ablation``: the online step timed per stage and per decoder layer,
the fast paths against the plain ones, the node's step per execution mode, the speed-against-
error sweep with its plot, and the ablation table. Tools: nothing in the library imports them."""
