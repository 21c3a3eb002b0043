"""GEM: Lie groups (``gem_head.lie``), the GEM head (``gem_head.head``), the paper's two-stage GEM
(``gem_head.two_stage``) and the group-feature ablation (``gem_head.ablation``); built on ``dynamics``."""
