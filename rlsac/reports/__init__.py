"""Reports: the paper's tables beside ours (``tables``), the paper's numbers (``paper``), figures (``figures``)."""
