"""The token network (`--policy.encoder=tokens`): ACT's token memory with a bottleneck on every token."""

from __future__ import annotations

import json

import pytest
import torch
from lerobot.policies.act.modeling_act import ACTDecoder, ACTEncoder

from helpers import BIN, TRAIN_ARGS, make_batch, make_config, run, with_rate_statistics
from lerobot_vib.configuration_vib import VIBConfigError
from lerobot_vib.modeling_vib import VIBPolicy
from lerobot_vib.scores import map_score, token_scores
from lerobot_vib.token_network import TokenNetwork

CAMERA = {"top": (3, 48, 64)}


def tokens_config(**overrides):
    return make_config(cameras=CAMERA, state_dim=5, encoder="tokens", backbone_layer="layer2", **overrides)


@pytest.fixture(scope="module")
def policy() -> VIBPolicy:
    torch.manual_seed(0)
    return with_rate_statistics(VIBPolicy(tokens_config())).eval()


def test_one_token_per_feature_map_cell_and_per_state_reusing_acts_encoder_and_decoder(policy):
    network = policy.model
    assert isinstance(network, TokenNetwork)
    assert isinstance(network.encoder, ACTEncoder) and isinstance(network.decoder, ACTDecoder)
    assert network.map_shape == (1, 6, 8)  # a layer2 trunk: stride 8 on 48x64
    assert network.n_tokens == 1 + 48
    posterior = network.encode(make_batch(policy.config, with_action=False))
    assert posterior.mean.shape == (2, 49, policy.config.latent_dim)


def test_the_rate_is_the_mean_of_the_token_rates_and_the_map_lays_the_cells_out_row_by_row(policy):
    network = policy.model
    posterior = network.encode(make_batch(policy.config, with_action=False))
    token_rates = network.token_rates(posterior)
    torch.testing.assert_close(network.rate(posterior), token_rates.mean(1))
    rate_map = network.rate_map(token_rates)
    assert rate_map.shape == (2, 1, 6, 8)
    assert rate_map[1, 0, 2, 5] == token_rates[1, 1 + 2 * 8 + 5]  # after the one state token
    scores = token_scores(token_rates, network.n_1d_tokens, None, None)
    torch.testing.assert_close(scores["image_rate"], token_rates[:, 1:].mean(1))  # exact, no counterfactual
    torch.testing.assert_close(scores["state_rate"], token_rates[:, 0])
    assert "map_score" not in scores  # needs the cells' training statistics


def test_a_per_cell_marginal_judges_each_cell_against_its_own():
    torch.manual_seed(0)
    network = VIBPolicy(tokens_config(token_marginal="cell")).model.eval()
    bottleneck = network.image_bottleneck
    assert bottleneck.marginal_mean.shape == (48, network.config.latent_dim)
    posterior = network.encode(make_batch(network.config, with_action=False))
    before = network.token_rates(posterior)
    with torch.no_grad():
        bottleneck.marginal_mean[7] += 3.0  # cell 7 now expects something else
    after = network.token_rates(posterior)
    changed = torch.nonzero((after - before).abs().amax(0) > 1e-6).flatten().tolist()
    assert changed == [1 + 7]


def test_training_samples_z_and_evaluation_decodes_the_posterior_mean():
    torch.manual_seed(0)
    policy = VIBPolicy(tokens_config())
    batch = make_batch(policy.config)
    policy.train()
    first, second = policy.model(batch, sample=True).actions, policy.model(batch, sample=True).actions
    assert not torch.equal(first, second)
    policy.eval()
    torch.testing.assert_close(policy.predict_action_chunk(batch), policy.predict_action_chunk(batch))


def test_the_loss_is_l1_plus_beta_rate_and_its_gradient_reaches_the_trunk_through_the_bottleneck():
    torch.manual_seed(0)
    policy = VIBPolicy(tokens_config(beta=0.5)).train()
    batch = make_batch(policy.config)
    loss, info = policy.forward(batch)
    assert loss.item() == pytest.approx(info["l1_loss"] + 0.5 * info["rate"], rel=1e-5)
    loss.backward()
    assert policy.model.backbone.conv1.weight.grad.abs().sum() > 0
    groups = policy.get_optim_params()
    trunk = {id(p) for p in policy.model.backbone.parameters()}
    assert {id(p) for p in groups[1]["params"]} == trunk  # the trunk's own learning rate, as ACT's


def test_the_map_score_is_the_largest_cell_z_score():
    rates = torch.tensor([[1.0, 2.0, 10.0], [1.0, 2.0, 3.0]])
    mean, std = torch.tensor([1.0, 2.0, 2.0]), torch.tensor([1.0, 1.0, 4.0])
    torch.testing.assert_close(map_score(rates, mean, std), torch.tensor([2.0, 0.25]))
    torch.testing.assert_close(map_score(rates, mean, std, top_k=2), torch.tensor([1.0, 0.125]))


def test_a_cell_whose_rate_falls_raises_the_low_map_score_and_not_the_map_score():
    mean, std = torch.ones(4), torch.full((4,), 0.5)
    rates = torch.tensor([[1.0, 1.0, 1.0, -2.0]])  # one cell 6 std below what it showed in training
    scores = token_scores(torch.cat([torch.ones(1, 1), rates], 1), 1, mean, std)
    torch.testing.assert_close(scores["low_map_score"], torch.tensor([6.0]))
    torch.testing.assert_close(scores["map_score"], torch.tensor([0.0]))


def test_a_cell_that_falls_and_one_that_rises_both_raise_the_abs_map_score():
    mean, std = torch.ones(4), torch.full((4,), 0.5)
    falls = torch.tensor([[1.0, 1.0, 1.0, -2.0]])  # 6 std below training
    rises = torch.tensor([[1.0, 1.0, 1.0, 3.0]])  # 4 std above
    for rates, expected in ((falls, 6.0), (rises, 4.0)):
        scores = token_scores(torch.cat([torch.ones(1, 1), rates], 1), 1, mean, std)
        torch.testing.assert_close(scores["abs_map_score"], torch.tensor([expected]))
        # at k = 1 it is the larger of the two one-sided scores, which is how recorded traces give it back
        torch.testing.assert_close(scores["abs_map_score"], torch.maximum(scores["map_score"], scores["low_map_score"]))
    quiet = token_scores(torch.cat([torch.ones(1, 1), torch.ones(1, 4)], 1), 1, mean, std)
    torch.testing.assert_close(quiet["abs_map_score"], torch.tensor([0.0]))


def test_select_action_leaves_the_rate_map_and_every_token_score(policy):
    policy.reset()
    action = policy.select_action(make_batch(policy.config, with_action=False))
    step = policy.last_step
    assert action.shape == (2, 3) and step.rate_map.shape == (2, 1, 6, 8)
    assert {"rate", "image_rate", "low_image_rate", "state_rate"} <= set(step.scores)


def test_a_saved_token_policy_acts_identically_after_loading(policy, tmp_path):
    policy.save_pretrained(tmp_path)
    loaded = VIBPolicy.from_pretrained(tmp_path)
    batch = make_batch(policy.config, with_action=False)
    torch.testing.assert_close(loaded.predict_action_chunk(batch), policy.predict_action_chunk(batch))
    assert json.loads((tmp_path / "config.json").read_text())["encoder"] == "tokens"


def test_the_pooled_network_keeps_its_parameters_and_buffers(policy):
    """Checkpoints of the paper's network load as before: no token-network tensor appears in them."""
    pooled = VIBPolicy(make_config()).state_dict()
    assert "state_embedding_mean" in pooled and not any("map_cell" in k for k in pooled)
    assert pooled["model.bottleneck.marginal_mean"].shape == (make_config().latent_dim,)
    assert "map_cell_mean" in policy.state_dict() and "state_embedding_mean" not in policy.state_dict()


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (dict(encoder="transformer"), "`encoder` must be one of"),
        (dict(encoder="tokens", token_marginal="camera"), "`token_marginal` must be one of"),
        (dict(encoder="tokens", n_decoder_layers=0), "n_decoder_layers"),
        (dict(encoder="tokens", rnd_input="pooled"), "token network has none"),
    ],
)
def test_bad_token_network_settings_are_refused_by_name(overrides, message):
    with pytest.raises(VIBConfigError, match=message):
        make_config(**overrides)


def test_a_token_score_on_the_pooled_network_is_refused():
    with pytest.raises(ValueError, match="only the token network"):
        VIBPolicy(make_config(uncertainty_score="map_score"))


@pytest.mark.slow
def test_lerobot_train_and_calibrate_give_the_token_network_its_map_statistics(tiny_dataset_root, tmp_path):
    out = tmp_path / "run"
    run(
        [
            str(BIN / "lerobot-train"),
            *TRAIN_ARGS,
            "--policy.encoder=tokens",
            "--policy.backbone_layer=layer2",
            "--dataset.repo_id=local/tiny",
            f"--dataset.root={tiny_dataset_root}",
            "--steps=2",
            "--save_freq=2",
            f"--output_dir={out}",
        ]
    )
    ckpt = out / "checkpoints" / "last" / "pretrained_model"
    run(
        [
            str(BIN / "lerobot-vib-calibrate"),
            f"--policy.path={ckpt}",
            "--dataset.repo_id=local/tiny",
            f"--dataset.root={tiny_dataset_root}",
            "--rnd_steps=20",
        ]
    )
    calibrated = ckpt.with_name("pretrained_model_calibrated")
    means = json.loads((calibrated / "config.json").read_text())["calibration"]["score_means"]
    assert {"image_rate", "state_rate", "map_score", "low_map_score", "abs_map_score", "embedding_rnd"} <= set(means)
    from lerobot.configs.policies import PreTrainedConfig

    config = PreTrainedConfig.from_pretrained(calibrated)
    config.uncertainty_score = "map_score"
    loaded = VIBPolicy.from_pretrained(calibrated, config=config)
    assert torch.isfinite(loaded.map_cell_mean).all() and (loaded.map_cell_std > 0).all()
    assert loaded.map_cell_mean.shape == (6 * 8,)
