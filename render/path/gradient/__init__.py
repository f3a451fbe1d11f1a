"""What paths carry, and its gradient: every vertex recomputed on the tape (``transport``:
the reference), and path replay one depth at a time (``replay``), its windows compiled by
``minidiff.compile`` (``window``)."""
