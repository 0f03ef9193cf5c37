"""``fbgforce demo``: the whole chain on the built-in simulator (:mod:`fbgforce.demo.cli`)."""
