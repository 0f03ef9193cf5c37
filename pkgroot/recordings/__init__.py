"""Recordings: the dataset format and every way into it.

==================  ============================================================================
``dataset``         the recording type, its CSV and npz files and their validation; ``load``
                    reads rosbag2 logs too
``bag``             rosbag2 logs (``.mcap`` or a bag directory) read into columns
``labimport``       a lab's interrogator and stage logs joined into one dataset
``labalign``        the stage clock aligned to the interrogator's (offset and drift)
``tare``            the unloaded baseline of a recording
``protocol``        the stage program a lab records
``cli``             the ``import`` and ``protocol`` commands
==================  ============================================================================
"""
