"""The detector: the paper's GMM colour model (Section III-C), detection, and its service."""
