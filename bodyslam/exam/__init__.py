"""Whole exams (``bodyslam batch``): folders, videos and manifests in resumable, parallel chunks of the visual
engine, fused with RF when it is given, with marked frames."""
