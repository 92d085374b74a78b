"""``python -m torchsde_lti.train``: the main job (a shim; the code is :mod:`torchsde_lti.training.train`)."""

from torchsde_lti.training.train import config_path, main, restart_learner, train

__all__ = ["config_path", "main", "restart_learner", "train"]

if __name__ == "__main__":
    main()
