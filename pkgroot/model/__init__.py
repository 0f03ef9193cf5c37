"""The model: what a model directory holds and the float64 engine that runs it.

==================  ============================================================================
``artifact``        the model's parts: ``Preprocess``, ``Memory``, ``InUse``, ``MLP``,
                    ``HierarchicalModel``, ``CalibrationRecordings``
``modeldir``        the directory on disk: ``save``, ``load``, ``load_calibration``,
                    ``check_export``
``freshness``       whether an export belongs to the float model beside it
``decision``        the contact decision over time and its CUSUM calibration
``floatref``        the float64 reference engine, stage by stage as the C runtimes run it
                    (front, filter, memory, nets, decision, rest tracker, hold): ``predict``,
                    ``FloatPipeline``
==================  ============================================================================
"""
