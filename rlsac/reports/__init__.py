"""Reports: the paper's tables beside ours (``tables``), the paper's numbers (``paper``), figures (``figures``). They
read the results (rlsac.evaluation.results) and the protocol's names (rlsac.layout.protocol), never a runner."""
