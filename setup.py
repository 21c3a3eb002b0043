from setuptools import find_packages, setup

setup(
    name="gem-pets",
    version="0.2.0",
    description="PETS model-based RL with a swappable dynamics head: delta-state or GEM (Group Enhanced Model)",
    license="MIT",
    packages=find_packages(
        include=[
            "dynamics",
            "dynamics.*",
            "pets",
            "pets.*",
            "gem_head",
            "gem_head.*",
            "envs",
            "envs.*",
        ]
    ),
    py_modules=["run_pets"],
    python_requires=">=3.10",
    install_requires=[
        # A range that 2.13.0 satisfies: with the CPU wheel installed first nothing more is pulled.
        "torch>=2.3",
        "gymnasium[mujoco]>=1.0",
        "numpy>=1.24",
        "omegaconf>=2.3",
        # config values and lists on the command line (pets.config)
        "pyyaml>=6",
        "tqdm>=4.60",
        # Reward curves and the experiment plots.
        "matplotlib>=3.7",
        # A/B statistics (IQM, stratified-bootstrap CIs, probability of improvement): Agarwal et al.'s own library.
        "rliable>=1.2",
        # rliable 1.2 needs arch 7 (arch 8 dropped the random_state argument rliable passes), and arch 7 does not
        # import under pandas 3.
        "arch>=7,<8",
        "pandas<3",
    ],
    extras_require={
        # Tests: property-based tests (hypothesis) and scipy as an independent rotation reference.
        # ruff pinned: .ci/run checks lint and format, and the format can change between releases.
        # SAC data like the GEM paper's (pets.collect --policy sac:STEPS / sb3:AGENT.zip): stable-baselines3.
        "sac": ["stable-baselines3>=2.3"],
        # pets.compare --backend ray: sweeps on a Ray cluster (or a local Ray instance), docs/cluster.md.
        "ray": ["ray>=2.40"],
        # Looking at runs: episode videos (imageio + its ffmpeg plugin, which ships an ffmpeg binary) and TensorBoard
        # event files (tensorboard, for torch.utils.tensorboard). pets.visualize needs neither (MuJoCo + matplotlib).
        "viz": ["imageio>=2.28", "imageio-ffmpeg>=0.4.9", "tensorboard>=2.14"],
        # The video and event-file tests read MP4s back with imageio and events with TensorBoard's reader.
        "dev": [
            "pytest>=7",
            # The README's test command runs the suite on 2 workers: 491 s instead of 765-806 s on 2 Zen 3 cores.
            "pytest-xdist>=3",
            "hypothesis>=6",
            "scipy>=1.10",
            "ruff==0.17.6",
            "stable-baselines3>=2.3",
            "imageio>=2.28",
            "imageio-ffmpeg>=0.4.9",
            "tensorboard>=2.14",
            "ray>=2.40",
        ],
    },
    # Every command also runs as ``python -m MODULE`` (``python run_pets.py`` for run-pets).
    entry_points={
        "console_scripts": [
            "run-pets=run_pets:main",
            "pets-compare=pets.experiments.cli:main",
            "pets-collect=pets.collect:main",
            "pets-train=pets.train:main",
            "pets-evaluate=pets.evaluate:main",
            "pets-openloop=pets.openloop:main",
            "pets-oracle=pets.tools.oracle:main",
            "pets-visualize=pets.tools.visualize:main",
            "pets-onestep=pets.tools.onestep:main",
            "pets-bench=pets.tools.bench:main",
        ]
    },
)
