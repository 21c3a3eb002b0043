"""GEM: Lie groups (``gem_head.lie``), the GEM head (``gem_head.head``, a loop over the per-kind group codecs of
``gem_head.codecs``), ``gem-se``'s SE(2)/SE(3) root (``gem_head.se_root``), the paper's two-stage GEM
(``gem_head.two_stage``) and the group-feature ablation (``gem_head.ablation``); built on ``dynamics``."""
