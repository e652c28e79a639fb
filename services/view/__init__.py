"""``handkse view`` and ``handkse export``: the pipeline in Rerun, and recordings Foxglove can show."""
