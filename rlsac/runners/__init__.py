"""What runs the studies' stages: the DVC pipeline on Ray (pipeline), one stage (dvc_stage), its plan
(stage_status), remote storage (transfer) and the record's check (verify).
"""
