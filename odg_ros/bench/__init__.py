"""``odg bench`` and ``odg ablation``: the node's own step timed per camera set, per execution
mode and precision, per stage and per decoder layer (from the step's marks), the
speed-against-error sweep over configurations of that step with its plot, and the ablation
table. Tools: nothing in the library imports them."""
