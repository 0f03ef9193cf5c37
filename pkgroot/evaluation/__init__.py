"""Evaluation: one definition of the metrics, every inference engine behind one signature,
and the figures.

==================  ============================================================================
``metrics``         the accuracy metrics every command and benchmark scores with
``engines``         the engines (``float``, ``onnx``, ``fixed``, ``cfloat``, ``intref``) by name
``figures``         the pictures ``fbgforce demo`` ends with
``onset_bound``     how early any contact decision could find a recording's presses
==================  ============================================================================

``engines`` sits above the exporter and the runtime binding whose engines it names; the others
need neither, so the trainer can score with them.
"""
