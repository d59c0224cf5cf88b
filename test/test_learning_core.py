"""Learning core: context window, psi, losses and which parameters each loss trains."""

from dataclasses import asdict

import numpy as np
import pytest
import torch

from zeus_ros.core.agent import Agent, param_normaliser
from zeus_ros.learning_tools.train import family_config as make_config
from zeus_ros.core.config import (refuse_foreign_keys, setting_owners, settings_classes,
                                   settings_fields, SHARED_KEYS, ZeusConfig)
from zeus_ros.core.methods import METHODS, ParamScale
from zeus_ros.core.methods.zeus import w2_diag_gaussians
from zeus_ros.core.networks import ContextEncoder
from zeus_ros.core.replay import ReplayBuffer
from zeus_ros.core.window import ContextWindow, row_dim

OBS, ACT, K = 5, 2, 4
ROW = row_dim(OBS, ACT)


def tiny_config(method='zeus', **kw):
    base = dict(hidden_dim=32, context_dim=6, feature_dim=8, encoder_hidden=16,
                context_hidden=16, dynamics_hidden=16, decoder_hidden=8, context_length=K,
                batch_size_per_task=4, replay_capacity=200, num_threads=1)
    base.update(kw)
    return make_config('walker-walk-v0', 'cpu', method, **base)


def make_agent(method='zeus', **kw):
    torch.manual_seed(0)
    return Agent(tiny_config(method, **kw), OBS, ACT, ParamScale(0.8, 0.55))


def fill_replay(buf, steps=60, tasks=3, seed=0):
    """Interleave episodes of several tasks as the trainer does; return the true windows."""
    rng = np.random.default_rng(seed)
    windows = [ContextWindow(K, OBS, ACT) for _ in range(tasks)]
    truth = []
    for _ in range(steps):
        for i, w in enumerate(windows):
            if rng.random() < 0.1:
                w.clear()  # an episode boundary
            s, a, r, s2 = rng.normal(size=OBS), rng.uniform(-1, 1, ACT), rng.normal(), \
                rng.normal(size=OBS)
            before, continues = w.arrays(), w.fill > 0
            w.push(s, a, r, s2)
            buf.add(s, a, r, s2, False, i, 0.8 + 0.05 * i, continues)
            truth.append((before, w.arrays()))
    return truth


def make_batch(n=16, seed=0):
    buf = ReplayBuffer(64, OBS, ACT, K, ROW, seed=seed)
    fill_replay(buf, steps=20, tasks=3, seed=seed)
    return buf.sample(n)


def module(agent, name):
    return agent.modules()[name]


def grads_of(module):
    return [p.grad for p in module.parameters()]


def has_grad(module):
    return any(g is not None and g.abs().sum() > 0 for g in grads_of(module))


def no_grad(module):
    return all(g is None or g.abs().sum() == 0 for g in grads_of(module))


def zero_all(agent):
    for m in agent.modules().values():
        m.zero_grad(set_to_none=True)
    agent.log_alpha.grad = None


# -- context window ------------------------------------------------------------
def test_window_at_episode_start_is_empty_and_psi_gives_zero():
    w = ContextWindow(K, OBS, ACT)
    rows, mask = w.arrays()
    assert rows.shape == (K, ROW) and rows.dtype == np.float32
    assert mask.shape == (K,) and mask.dtype == bool and not mask.any()
    assert not rows.any()
    for agg in ('mean', 'sum', 'max'):
        psi = ContextEncoder(ROW, 6, 16, 2, agg)
        torch.nn.init.constant_(psi.net[-1].bias, 3.0)  # a nonzero code for any row
        out = psi(torch.from_numpy(rows)[None], torch.from_numpy(mask)[None])
        assert torch.equal(out, torch.zeros(1, 6)), agg


def test_window_keeps_last_k_of_episode_oldest_first_and_clears():
    w = ContextWindow(K, OBS, ACT)
    for t in range(K + 2):
        w.push(np.full(OBS, t), np.full(ACT, 0.5), float(t), np.full(OBS, t + 1))
        rows, mask = w.arrays()
        n = min(t + 1, K)
        assert w.fill == n and mask.sum() == n and mask[:n].all()
        assert not rows[n:].any()
        # rows hold s = the transition index: oldest first
        np.testing.assert_array_equal(rows[:n, 0], np.arange(t + 1 - n, t + 1))
        np.testing.assert_array_equal(rows[:n, OBS + ACT], np.arange(t + 1 - n, t + 1))
        np.testing.assert_array_equal(rows[:n, -1], np.arange(t + 2 - n, t + 2))
    w.clear()
    rows, mask = w.arrays()
    assert w.fill == 0 and not mask.any() and not rows.any()


def test_window_rejects_wrong_sizes():
    w = ContextWindow(K, OBS, ACT)
    with pytest.raises(ValueError):
        w.push(np.zeros(OBS + 1), np.zeros(ACT), 0.0, np.zeros(OBS))
    with pytest.raises(ValueError):
        w.push(np.zeros(OBS), np.zeros(ACT + 1), 0.0, np.zeros(OBS))


# -- psi -------------------------------------------------------------------------
def assert_order_and_padding_invariant(psi):
    """Check that shuffled rows or garbage in the padding leave psi's latent unchanged."""
    rows = torch.randn(3, K, ROW)
    mask = torch.tensor([[True, True, True, False], [True] * K, [True, False, False, False]])
    with torch.no_grad():
        out = psi(rows, mask)
        perm = torch.tensor([2, 0, 3, 1])
        assert torch.allclose(psi(rows[:, perm], mask[:, perm]), out, atol=1e-6)
        garbage = rows.clone()
        garbage[~mask] = 1e3
        assert torch.allclose(psi(garbage, mask), out, atol=1e-6)
        # and it is not trivially constant: changing a valid row changes the output
        changed = rows.clone()
        changed[:, 0] += 1.0
        assert not torch.allclose(psi(changed, mask), out)


@pytest.mark.parametrize('agg', ['mean', 'sum', 'max'])
def test_psi_is_permutation_invariant_and_ignores_padding(agg):
    torch.manual_seed(1)
    assert_order_and_padding_invariant(ContextEncoder(ROW, 6, 16, 2, agg))


def test_w2_closed_form():
    mu = torch.tensor([[0.0, 1.0]])
    ls = torch.log(torch.tensor([[1.0, 2.0]]))
    assert torch.allclose(w2_diag_gaussians(mu, ls, mu, ls), torch.zeros(1))
    mu2 = torch.tensor([[3.0, 5.0]])
    ls2 = torch.log(torch.tensor([[1.0, 4.0]]))
    expected = torch.sqrt(torch.tensor(9.0 + 16.0 + 4.0))
    assert torch.allclose(w2_diag_gaussians(mu, ls, mu2, ls2), expected)


# -- which loss trains what ------------------------------------------------------
def test_critic_loss_trains_critic_phi_psi_only():
    agent, b = make_agent(), make_batch()
    zero_all(agent)
    loss, _, _, _ = agent.critic_loss(b)
    loss.backward()
    for name in ('critic', 'phi', 'psi'):
        assert has_grad(module(agent, name)), name
    for name in ('actor', 'T', 'R', 'decoder', 'critic_target', 'phi_target', 'psi_target'):
        assert no_grad(module(agent, name)), name
    assert agent.log_alpha.grad is None


def test_actor_loss_trains_actor_only_and_alpha_loss_alpha_only():
    agent, b = make_agent(), make_batch()
    _, z, c, _ = agent.critic_loss(b)
    zero_all(agent)
    agent.critic.requires_grad_(False)
    actor_loss, alpha_loss, _ = agent.actor_and_alpha_loss(z, c)
    actor_loss.backward(retain_graph=True)
    assert has_grad(agent.actor)
    for name in ('phi', 'psi', 'critic', 'T', 'R', 'decoder'):
        assert no_grad(module(agent, name)), name
    assert agent.log_alpha.grad is None
    agent.actor.zero_grad(set_to_none=True)
    alpha_loss.backward()
    assert agent.log_alpha.grad is not None and agent.log_alpha.grad != 0
    assert no_grad(agent.actor)


def test_context_target_carries_no_gradient():
    agent, b = make_agent(), make_batch()
    z = agent.phi(b.obs)
    c = agent.method.psi(b.ctx_rows, b.ctx_mask)
    d = agent.method.context_target(z, b.action, c, c.flip(0))
    assert not d.requires_grad
    assert (d >= 0).all() and d.abs().sum() > 0


def test_context_loss_trains_psi_only():
    agent, b = make_agent(), make_batch()
    zero_all(agent)
    with torch.no_grad():
        z = agent.phi(b.obs)
    c = agent.method.psi(b.ctx_rows, b.ctx_mask)
    loss = agent.method.context_loss(z, b.action, c, torch.randperm(c.shape[0]))
    loss.backward()
    assert has_grad(agent.method.psi)
    for name in ('phi', 'T', 'R', 'critic', 'actor', 'decoder'):
        assert no_grad(module(agent, name)), name


def assert_model_loss_trains_psi_T_R_only(agent, loss, metrics):
    loss.backward()
    assert 'context_loss' in metrics
    for name in ('psi', 'T', 'R'):
        assert has_grad(module(agent, name)), name
    for name in ('phi', 'critic', 'actor', 'decoder'):
        assert no_grad(module(agent, name)), name


def test_model_loss_trains_psi_T_R_not_phi():
    agent, b = make_agent(), make_batch()
    zero_all(agent)
    loss, _, metrics = agent.method.model_loss(b, agent.phi(b.obs).detach())
    assert_model_loss_trains_psi_T_R_only(agent, loss, metrics)


def test_alpha_psi_zero_context_loss_leaves_psi_untouched():
    b = make_batch()
    perm = torch.randperm(b.obs.shape[0])
    grads = {}
    for alpha_psi in (0.0, 1.0):
        agent = make_agent(alpha_psi=alpha_psi)
        if alpha_psi == 0.0:
            def boom(*args, **kwargs):
                raise AssertionError('context loss evaluated with alpha_psi = 0')
            agent.method.context_loss = boom
        zero_all(agent)
        loss, _, metrics = agent.method.model_loss(b, agent.phi(b.obs).detach(), perm)
        loss.backward()
        assert ('context_loss' in metrics) == (alpha_psi > 0)
        grads[alpha_psi] = {n: [p.grad.clone() for p in module(agent, n).parameters()]
                            for n in ('psi', 'T', 'R')}
    # The context term changes psi's gradient, and only psi's: with it removed,
    # psi's gradient is exactly that of the dynamics + reward terms.
    assert any(not torch.allclose(a, c) for a, c in zip(grads[0.0]['psi'], grads[1.0]['psi'],
                                                        strict=True))
    for name in ('T', 'R'):
        for a, c in zip(grads[0.0][name], grads[1.0][name], strict=True):
            assert torch.allclose(a, c), name


def test_decoder_loss_does_not_move_psi():
    agent, b = make_agent(), make_batch()
    zero_all(agent)
    c = agent.method.psi(b.ctx_rows, b.ctx_mask)
    loss = agent.method.decoder_loss(c, b.param)
    loss.backward()
    assert has_grad(agent.method.decoder)
    assert no_grad(agent.method.psi) and no_grad(agent.phi)


def test_update_moves_the_right_things_and_targets_lag():
    agent, b = make_agent(), make_batch()
    before = {n: [p.detach().clone() for p in m.parameters()]
              for n, m in agent.modules().items()}
    m1 = agent.update(b)
    assert 'actor_loss' not in m1  # actor every 2 updates
    assert all(torch.equal(p, q) for p, q in zip(before['actor'], agent.actor.parameters(),
                                                 strict=True))
    assert all(torch.equal(p, q) for p, q in zip(
        before['critic_target'], agent.critic_target.parameters(), strict=True))
    m2 = agent.update(b)
    assert 'actor_loss' in m2 and np.isfinite([float(v) for v in m2.values()]).all()
    for name, params in before.items():
        moved = any(not torch.equal(p, q) for p, q in zip(
            params, agent.modules()[name].parameters(), strict=True))
        assert moved, name
    # targets are Polyak averages: moved, but far less than the online nets
    online = sum((p - q).abs().sum() for p, q in zip(before['critic'],
                                                     agent.critic.parameters(), strict=True))
    target = sum((p - q).abs().sum() for p, q in zip(
        before['critic_target'], agent.critic_target.parameters(), strict=True))
    assert 0 < target < online


def test_act_shapes_and_range():
    agent = make_agent()
    w = ContextWindow(K, OBS, ACT)
    rows, mask = w.arrays()
    a = agent.act(np.ones(OBS), rows, mask, deterministic=True)
    assert a.shape == (ACT,) and a.dtype == np.float64 and np.all(np.abs(a) <= 1)
    batch = agent.act(np.ones((3, OBS)), np.stack([rows] * 3), np.stack([mask] * 3))
    assert batch.shape == (3, ACT) and np.all(np.abs(batch) <= 1)


def test_replay_stores_windows_task_and_param():
    b = make_batch(n=16)
    assert b.ctx_rows.shape == (16, K, ROW) and b.ctx_rows.dtype == torch.float32
    assert b.ctx_mask.dtype == torch.bool and b.task.dtype == torch.int64
    # the next window has exactly one more valid row (up to k) than the one before s_t
    n_before, n_after = b.ctx_mask.sum(1), b.next_ctx_mask.sum(1)
    assert torch.equal(n_after, torch.clamp(n_before + 1, max=K))
    # and its newest row is the stored transition itself
    last = (n_after - 1).long()
    newest = b.next_ctx_rows[torch.arange(16), last]
    assert torch.allclose(newest[:, :OBS], b.obs)
    assert torch.allclose(newest[:, -OBS:], b.next_obs)
    assert torch.allclose(newest[:, OBS + ACT], b.reward)


@pytest.mark.parametrize('capacity', [500, 50])
def test_replay_rebuilds_exactly_the_trainers_windows(capacity):
    """Links, not copies: every sampled window equals ContextWindow's, ring overwrite too."""
    buf = ReplayBuffer(capacity, OBS, ACT, K, ROW, seed=3)
    truth = fill_replay(buf, steps=40, tasks=3, seed=3)
    idx = np.arange(buf.size)
    (cr, cm), (nr, nm) = buf.windows(idx)
    first_kept = len(truth) - buf.size   # serial of slot 0's oldest survivor
    for slot in idx:
        serial = int(buf.serial[slot])
        (tb, tbm), (ta, tam) = truth[serial]
        n_before = int(cm[slot].sum())
        # a window may only be shorter than the truth where the ring dropped its start
        assert n_before == tbm.sum() or serial - 3 * n_before < first_kept + 3 * K
        np.testing.assert_array_equal(cr[slot][:n_before], tb[tbm.sum() - n_before:tbm.sum()])
        if n_before == tbm.sum():
            np.testing.assert_array_equal(cr[slot], tb)
            np.testing.assert_array_equal(nr[slot], ta)
            np.testing.assert_array_equal(nm[slot], tam)


def test_replay_state_round_trip_keeps_windows():
    buf = ReplayBuffer(100, OBS, ACT, K, ROW, seed=1)
    fill_replay(buf, steps=20, tasks=2, seed=1)
    other = ReplayBuffer(100, OBS, ACT, K, ROW, seed=1)
    other.load_state_arrays(buf.state_arrays())
    idx = np.arange(buf.size)
    for a, b in zip(buf.windows(idx), other.windows(idx), strict=True):
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])


# -- the other methods ---------------------------------------------------------
def test_sac_has_no_context_and_its_critic_trains_phi():
    agent, b = make_agent('sac'), make_batch()
    assert agent.method.context_dim == 0 and set(agent.inference_modules()) == {'phi', 'actor'}
    zero_all(agent)
    loss, _, c, _ = agent.critic_loss(b)
    loss.backward()
    assert c.shape == (b.obs.shape[0], 0)
    assert has_grad(agent.critic) and has_grad(agent.phi)
    assert agent.method.decode(c) is None


def test_oracle_context_is_the_normalised_true_parameter():
    agent, b = make_agent('oracle'), make_batch()
    c = agent.method.encode(b.ctx_rows, b.ctx_mask, b.param)
    assert b.param.shape == (b.obs.shape[0], 1) and c.shape == b.param.shape
    assert torch.allclose(c, (b.param - 0.8) / 0.55)
    assert torch.allclose(agent.method.decode(c), c)
    with pytest.raises(ValueError):
        agent.method.encode(b.ctx_rows, b.ctx_mask, None)
    # different true values, same observation -> different actions (the policy sees it)
    rows, mask = ContextWindow(K, OBS, ACT).arrays()
    a1 = agent.act(np.ones(OBS), rows, mask, [0.8], deterministic=True)
    a2 = agent.act(np.ones(OBS), rows, mask, [1.35], deterministic=True)
    assert not np.allclose(a1, a2)


def test_zeus_id_psi_gets_no_critic_gradient_and_model_loss_trains_it():
    agent, b = make_agent('zeus-id', context_length=K), make_batch()
    assert not agent.method.critic_trains_context
    zero_all(agent)
    loss, _, _, _ = agent.critic_loss(b)
    loss.backward()
    assert has_grad(agent.critic) and has_grad(agent.phi)
    assert no_grad(agent.method.psi)
    zero_all(agent)
    loss, _, metrics = agent.method.model_loss(b)
    assert_model_loss_trains_psi_T_R_only(agent, loss, metrics)


def test_zeus_id_critic_grad_ablation_lets_the_critic_train_psi():
    agent, b = make_agent('zeus-id', context_length=K, context_critic_grad=True), make_batch()
    zero_all(agent)
    loss, _, _, _ = agent.critic_loss(b)
    loss.backward()
    assert has_grad(agent.method.psi)


def test_zeus_id_reads_deltas():
    """With context_input='delta' psi sees s' - s, not s'.

    Shifting s and s' together leaves the delta part unchanged, while the
    raw-transition ablation sees the shift there.
    """
    from zeus_ros.core.methods.zeus_id import transition_features
    rows = torch.randn(2, K, ROW)
    shifted = rows.clone()
    shifted[..., -OBS:] += 1.0
    shifted[..., :OBS] += 1.0
    d0, d1 = transition_features(rows, OBS, True), transition_features(shifted, OBS, True)
    assert torch.allclose(d0[..., -OBS:], d1[..., -OBS:], atol=1e-6)
    assert not torch.allclose(transition_features(shifted, OBS, False)[..., -OBS:],
                              rows[..., -OBS:])


ALL_METHODS = ['zeus', 'zeus-no-context-loss', 'sac', 'oracle', 'zeus-id', 'cadm', 'up-osi',
               'hyperdynamics', 'zeus-osi', 'rma']


@pytest.mark.parametrize('method', ALL_METHODS)
def test_every_method_updates_and_acts(method):
    agent, b = make_agent(method, context_length=K), make_batch()
    for _ in range(2):
        metrics = agent.update(b)
    assert np.isfinite([float(v) for v in metrics.values()]).all()
    rows, mask = ContextWindow(K, OBS, ACT).arrays()
    a = agent.act(np.ones(OBS), rows, mask, [1.0], deterministic=True)
    assert a.shape == (ACT,) and np.all(np.abs(a) <= 1)


def test_cadm_backward_loss_reaches_its_encoder_and_the_critic_does_not():
    agent, b = make_agent('cadm'), make_batch()
    zero_all(agent)
    agent.critic_loss(b)[0].backward()
    assert no_grad(agent.method.psi)
    m = agent.method
    c = m.psi(b.ctx_rows, b.ctx_mask)
    x, delta = m.standardised_step(b)
    o, norm = OBS, m.psi.norm
    x_next = (b.next_obs - norm.mean[:o]) / (norm.var[:o].sqrt() + 1e-4)
    from zeus_ros.core.methods.common import gaussian_nll
    zero_all(agent)
    gaussian_nll(*m.models['T_backward'](x_next, b.action, c), -delta).backward()
    assert has_grad(m.psi) and has_grad(m.models['T_backward'])
    assert no_grad(m.models['T_forward'])


def test_up_osi_trains_on_the_true_parameter_and_deploys_its_estimate():
    agent, b = make_agent('up-osi', osi_warmup_updates=1), make_batch()
    m = agent.method
    c = m.encode(b.ctx_rows, b.ctx_mask, b.param)
    assert torch.allclose(c, (b.param - 0.8) / 0.55)   # UP sees the truth in training
    zero_all(agent)
    agent.critic_loss(b)[0].backward()
    assert no_grad(m.psi)                                      # no policy gradient into OSI
    assert torch.equal(m.deployed_context(b.ctx_rows, b.ctx_mask, b.param),
                       m.psi(b.ctx_rows, b.ctx_mask))
    assert torch.equal(m.acting_context(b.ctx_rows, b.ctx_mask, b.param), c)  # warm-up
    agent.update(b)
    assert torch.equal(m.acting_context(b.ctx_rows, b.ctx_mask, b.param),
                       m.psi(b.ctx_rows, b.ctx_mask))        # after it, OSI acts
    zero_all(agent)
    loss, _, metrics = m.model_loss(b)
    loss.backward()
    assert 'osi_loss' in metrics and has_grad(m.psi)
    for name in ('phi', 'critic', 'actor'):
        assert no_grad(module(agent, name)), name


def test_rma_teacher_is_shaped_by_td_and_the_adaptation_module_only_by_its_regression():
    agent, b = make_agent('rma', rma_student_after_updates=1, context_length=K), make_batch()
    m = agent.method
    z = m.encode(b.ctx_rows, b.ctx_mask, b.param)
    assert z.shape == (b.param.shape[0], 6)                  # extrinsics, not the parameter
    zero_all(agent)
    agent.critic_loss(b)[0].backward()
    assert has_grad(m.mu) and no_grad(m.psi)                 # TD trains mu, never psi
    zero_all(agent)
    loss, estimate, metrics = m.model_loss(b)
    loss.backward()
    assert 'adaptation_loss' in metrics and has_grad(m.psi)
    assert no_grad(m.mu)                                     # the student never moves the teacher
    for name in ('phi', 'critic', 'actor'):
        assert no_grad(module(agent, name)), name
    assert torch.equal(m.acting_context(b.ctx_rows, b.ctx_mask, b.param), z)  # teacher acts
    agent.update(b)
    assert torch.equal(m.acting_context(b.ctx_rows, b.ctx_mask, b.param),
                       m.psi(b.ctx_rows, b.ctx_mask))         # then its own estimates do
    assert torch.equal(m.deployed_context(b.ctx_rows, b.ctx_mask, None),
                       m.psi(b.ctx_rows, b.ctx_mask))


def actor_loss_of(agent, b):
    torch.manual_seed(1)            # the same action noise for every call
    _, z, c, _ = agent.critic_loss(b)
    c_actor = agent.method.actor_context(b, c)
    return agent.actor_and_alpha_loss(z, c, c_actor)[0].item()


@pytest.mark.parametrize('asymmetric', [False, True])
def test_rma_asymmetric_actor_reads_the_estimate_and_the_critic_the_teacher(asymmetric):
    agent, b = make_agent('rma', rma_student_after_updates=1, rma_asymmetric=asymmetric,
                          context_length=K), make_batch()
    m = agent.method
    teacher = m.encode(b.ctx_rows, b.ctx_mask, b.param)
    assert torch.equal(m.actor_context(b, teacher), teacher)    # before the switch: teacher
    agent.update(b)                                              # past the switch
    estimate = m.psi(b.ctx_rows, b.ctx_mask)
    read = m.actor_context(b, teacher)
    following = m.actor_context(b, teacher, following=True)
    assert torch.equal(read, estimate if asymmetric else teacher)
    assert torch.equal(following, m.psi(b.next_ctx_rows, b.next_ctx_mask)
                       if asymmetric else teacher)
    before = actor_loss_of(agent, b)
    with torch.no_grad():                                        # move psi alone
        for p in m.psi.parameters():
            p.add_(0.5)
    assert (actor_loss_of(agent, b) != before) == asymmetric     # the actor depends on psi
    zero_all(agent)
    agent.critic_loss(b)[0].backward()
    assert no_grad(m.psi)                                        # TD never trains psi


def test_rma_raw_parameter_ablation_regresses_the_normalised_parameter():
    agent, b = make_agent('rma', rma_latent=False, context_length=K), make_batch()
    m = agent.method
    assert m.mu is None and not m.critic_trains_context and m.context_dim == 1
    assert torch.allclose(m.encode(b.ctx_rows, b.ctx_mask, b.param), (b.param - 0.8) / 0.55)
    assert m.decode(m.psi(b.ctx_rows, b.ctx_mask)).shape == (b.param.shape[0], 1)


def test_temporal_psi_reads_order_and_ignores_padding():
    agent = make_agent('zeus-id', context_encoder='temporal')
    psi = agent.method.psi
    assert psi.temporal
    rows = torch.randn(2, K, ROW)
    mask = torch.ones(2, K, dtype=torch.bool)
    mask[1, K - 2:] = False
    c = psi(rows, mask)
    padded = rows.clone()
    padded[1, K - 2:] = 1e3                       # what the padding holds does not matter
    assert torch.allclose(psi(padded, mask), c, atol=1e-6)
    assert not torch.allclose(psi(rows.flip(1), mask.flip(1)), c, atol=1e-4)  # order does


def test_hyperdynamics_generates_per_context_weights_trained_through_the_encoder():
    agent, b = make_agent('hyperdynamics'), make_batch()
    m = agent.method
    x = torch.randn(3, OBS + ACT)
    c = torch.randn(3, 6)
    mu_a, _ = m.models['hyper'](c, x)
    mu_b, _ = m.models['hyper'](c.flip(0), x)
    assert not torch.allclose(mu_a, mu_b)   # another context, another dynamics model
    zero_all(agent)
    loss, _, _ = m.model_loss(b)
    loss.backward()
    assert has_grad(m.psi) and has_grad(m.models['hyper'])
    zero_all(agent)
    agent.critic_loss(b)[0].backward()
    assert has_grad(m.psi)   # trained jointly with the policy (context_critic_grad)


def test_zeus_id_identification_weight_routes_the_regression_into_psi_only():
    b = make_batch()
    after = {}
    for weight in (0.0, 1.0):
        agent = make_agent('zeus-id', context_length=K, id_weight=weight)
        torch.manual_seed(7)
        agent.method.update(b, agent.phi(b.obs).detach(), 1)
        after[weight] = {n: [p.detach().clone() for p in module(agent, n).parameters()]
                         for n in ('psi', 'T', 'R', 'decoder')}
    moved = lambda n: any(not torch.equal(p, q) for p, q in zip(  # noqa: E731
        after[0.0][n], after[1.0][n], strict=True))
    assert moved('psi')                       # the regression shaped psi
    assert not moved('T') and not moved('R')  # and nothing else of the model
    assert not moved('decoder')               # the decoder learns the same either way


def test_zeus_osi_reads_its_estimate_off_the_latent_and_learns_it_through_psi_only():
    agent, b = make_agent('zeus-osi', context_length=K), make_batch()
    m = agent.method
    assert m.decoder is None and m.context_dim == 6
    c = m.psi(b.ctx_rows, b.ctx_mask)
    assert torch.equal(m.decode(c), c[:, :1])          # the estimate IS the latent's head
    zero_all(agent)
    agent.critic_loss(b)[0].backward()
    assert no_grad(m.psi)                              # no TD gradient, as zeus-id
    # Its loss is zeus-id's plus id_weight * MSE of that head, and only psi learns from it.
    from zeus_ros.core.methods.zeus_id import ZeusIdMethod
    perm = torch.randperm(c.shape[0])
    torch.manual_seed(1)
    loss, c, metrics = m.model_loss(b, perm)
    torch.manual_seed(1)
    base = ZeusIdMethod.model_loss(m, b, perm)[0]
    head = ((m.decode(c) - m.param.normalise(b.param)) ** 2).mean()
    assert torch.allclose(loss - base, m.settings.id_weight * head, atol=1e-4)
    assert 'decoder_loss' in metrics
    zero_all(agent)
    head.backward()
    assert has_grad(m.psi) and no_grad(m.models['T']) and no_grad(m.models['R'])
    for name in ('phi', 'critic', 'actor'):
        zero_all(agent)
        m.model_loss(b)[0].backward()
        assert no_grad(module(agent, name)), name
    with pytest.raises(ValueError, match='id_weight > 0'):
        make_agent('zeus-osi', id_weight=0.0)


def test_the_ablation_refuses_a_context_loss_weight_at_configuration():
    assert tiny_config('zeus-no-context-loss').alpha_psi == 0.0
    with pytest.raises(ValueError, match='alpha_psi = 0 ablation'):
        tiny_config('zeus-no-context-loss', alpha_psi=1.0)


def test_a_method_with_its_own_update_must_say_so():
    from zeus_ros.core.methods.base import ContextMethod

    with pytest.raises(TypeError, match='has_own_update'):
        class Forgetful(ContextMethod):   # noqa: F841 (defining it is the test)
            def update(self, batch, z, step):
                return {}

    class Declared(ContextMethod):
        has_own_update = True

        def update(self, batch, z, step):
            return {}
    assert Declared.has_own_update


@pytest.mark.parametrize('method', ALL_METHODS)
def test_the_method_update_runs_exactly_when_the_method_has_one(method, monkeypatch):
    agent, b = make_agent(method, context_length=K), make_batch()
    calls = []
    real = agent.method.update
    monkeypatch.setattr(agent.method, 'update', lambda *a: calls.append(1) or real(*a))
    agent.update(b)
    assert len(calls) == (1 if agent.method.has_own_update else 0)
    assert agent.method.has_own_update == (method not in ('sac', 'oracle'))


def test_relational_psi_is_order_and_padding_invariant_and_reads_the_other_rows():
    agent = make_agent('zeus-id', context_encoder='relational')
    psi = agent.method.psi
    with torch.no_grad():   # give the standardiser some statistics
        psi.norm.observe(torch.randn(64, ROW))
    assert_order_and_padding_invariant(psi)
    # A mean of independent per-row codes is additive over rows: for two-row
    # windows {a, b} + {c, d} == {a, d} + {c, b}. Relational codes are not: a
    # row's code depends on the row beside it.
    a, b, c, d = torch.randn(4, ROW)
    full = torch.ones(1, 2, dtype=torch.bool)

    def pair(r1, r2, module):
        with torch.no_grad():
            return module(torch.stack([r1, r2])[None], full)[0]

    plain = make_agent('zeus-id').method.psi
    plain.norm.load_state_dict(psi.norm.state_dict())
    for module, additive in ((plain, True), (psi, False)):
        left = pair(a, b, module) + pair(c, d, module)
        right = pair(a, d, module) + pair(c, b, module)
        assert torch.allclose(left, right, atol=1e-5) == additive
    assert agent.config.method_settings.context_encoder == 'relational'
    with pytest.raises(ValueError, match='context_encoder'):
        tiny_config('zeus-id', context_encoder='attention')


@pytest.mark.parametrize('method,extra', [('zeus', {}), ('zeus-id', {}), ('cadm', {}),
                                          ('hyperdynamics', {}), ('up-osi', {}),
                                          ('zeus-id', {'context_encoder': 'relational'}),
                                          ('oracle', {}), ('sac', {}), ('zeus-osi', {})])
def test_encode_pair_is_the_two_windows_latents_from_one_pass(method, extra):
    agent, b = make_agent(method, **extra), make_batch()
    m = agent.method
    norm = getattr(getattr(m, 'psi', None), 'norm', None)
    if norm is not None:   # standardising statistics away from the identity
        norm.observe(b.ctx_rows[b.ctx_mask] * 3.0 + 1.0)
    with torch.no_grad():
        want_c = m.encode(b.ctx_rows, b.ctx_mask, b.param)
        want_cn = m.encode(b.next_ctx_rows, b.next_ctx_mask, b.param)
    c, cn = m.encode_pair(b, grad=True)
    assert torch.allclose(c, want_c, atol=1e-5) and torch.allclose(cn, want_cn, atol=1e-5)
    assert not cn.requires_grad
    assert c.requires_grad == (method in ('zeus', 'zeus-id', 'cadm', 'hyperdynamics',
                                          'zeus-osi'))


@pytest.mark.parametrize('method', ['oracle', 'zeus', 'zeus-id', 'up-osi', 'zeus-osi'])
def test_two_parameters_travel_as_columns_through_every_parameter_user(method):
    """A family with two parameters (Sawyer-Peg's goal x, y): contexts, decoders and losses."""
    scale = param_normaliser([(0.44, -0.08), (0.61, 0.08), (0.5, 0.0)])
    assert scale.offset == (0.44, -0.08) and scale.scale == pytest.approx((0.17, 0.16))
    torch.manual_seed(0)
    agent = Agent(tiny_config(method), OBS, ACT, scale)
    buf = ReplayBuffer(64, OBS, ACT, K, ROW, seed=0, param_dim=2)
    rng = np.random.default_rng(0)
    for t in range(40):
        goal = ((0.44, -0.08), (0.61, 0.08))[t % 2]
        buf.add(rng.normal(size=OBS), rng.uniform(-1, 1, ACT), rng.normal(),
                rng.normal(size=OBS), False, t % 2, goal, t >= 2)
    b = buf.sample(16)
    assert b.param.shape == (16, 2)
    metrics = agent.update(b)
    assert all(torch.isfinite(v).all() for v in metrics.values())
    latent = agent.method.deployed_context(b.ctx_rows, b.ctx_mask, b.param)
    assert agent.method.decode(latent).shape == (16, 2)
    if agent.method.needs_true_param or method == 'up-osi':
        assert agent.method.context_dim == 2
    rows, mask = ContextWindow(K, OBS, ACT).arrays()
    assert agent.act(np.ones(OBS), rows, mask, (0.5, 0.0), deterministic=True).shape == (ACT,)


def test_a_replay_saved_with_one_dimensional_parameters_loads_as_one_column():
    """Buffers saved before parameters were vectors (param [n]) resume unchanged."""
    buf = ReplayBuffer(64, OBS, ACT, K, ROW, seed=0)
    fill_replay(buf, steps=10, tasks=2)
    arrays = buf.state_arrays()
    arrays['replay.param'] = arrays['replay.param'][:, 0]   # the old layout
    restored = ReplayBuffer(64, OBS, ACT, K, ROW, seed=0)
    restored.load_state_arrays(arrays)
    np.testing.assert_array_equal(restored.param, buf.param)


@pytest.mark.parametrize('method', sorted(METHODS))
def test_every_method_declares_the_metrics_its_update_returns(method):
    """The train log's columns come from these names: an undeclared metric is a late column."""
    agent, b = make_agent(method), make_batch()
    returned = set(agent.update(b)) | set(agent.update(b))   # the actor steps every 2nd update
    silent = {'context_loss'} if agent.config.alpha_psi == 0 else set()   # the ablation's
    assert returned == set(agent.metric_names()) - silent
    assert len(agent.metric_names()) == len(set(agent.metric_names()))


def test_each_method_owns_its_settings_and_the_shared_config_does_not_hold_them():
    owners = setting_owners()
    assert not set(owners) & set(SHARED_KEYS)   # one flat namespace on disk
    for key in ('backward_weight', 'osi_warmup_updates', 'rma_latent',
                'rma_student_after_updates', 'hyper_model_hidden', 'metric_normalise',
                'dynamics_loss'):
        assert len({METHODS[m].settings_class.__module__ for m in owners[key]}) == 1, key
    assert set(owners['context_encoder']) == {'zeus-id', 'zeus-osi', 'cadm', 'up-osi',
                                              'hyperdynamics', 'rma'}
    for name, method in METHODS.items():   # every preset names a field the method has
        refuse_foreign_keys(name, method.config_defaults)
    assert make_agent('cadm', backward_weight=0.25).method.settings.backward_weight == 0.25
    with pytest.raises(ValueError, match='backward_weight is a setting of method cadm'):
        tiny_config('zeus', backward_weight=0.25)


def test_an_old_flat_config_with_every_methods_keys_still_builds_each_method():
    """Checkpoints written before the split hold every method's settings in one dict."""
    every = {k: v for cls in settings_classes() for k, v in asdict(cls()).items()}
    for name in METHODS:
        flat = {**tiny_config(name).to_dict(), **every, 'method': name}
        if name == 'zeus-no-context-loss':
            flat['alpha_psi'] = 0.0
        cfg = ZeusConfig.from_dict(flat)
        assert type(cfg.method_settings) is METHODS[name].settings_class
        assert set(cfg.to_dict()) == set(SHARED_KEYS) | set(settings_fields(name))
        assert ZeusConfig.from_dict(cfg.to_dict()) == cfg
    zeus = {**tiny_config('zeus').to_dict(), **every}
    with pytest.raises(ValueError, match='context_input'):   # another method's key, bad value
        ZeusConfig.from_dict({**zeus, 'context_input': 'bogus'})
    with pytest.raises(ValueError, match='unknown config keys'):
        ZeusConfig.from_dict({**zeus, 'no_such_key': 1})


@pytest.mark.parametrize('method', ['rma', 'up-osi', 'zeus-id'])
def test_a_context_trained_without_the_reward_ignores_its_column_bit_for_bit(method):
    """context_reward=false: a NaN reward (a robot's window) gives the same latent (#49)."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    rows = torch.as_tensor(rng.normal(size=(3, K, ROW)), dtype=torch.float32)
    mask = torch.ones(3, K, dtype=torch.bool)
    unknown = rows.clone()
    unknown[..., OBS + ACT] = float('nan')          # the reward column of concat(s, a, r, s')
    for reads in (False, True):
        agent = Agent(tiny_config(method, context_reward=reads), OBS, ACT)
        psi = agent.method.psi
        features = psi.features(rows)
        psi.norm.observe(features.reshape(-1, features.shape[-1]))
        known = agent.method.deployed_context(rows, mask, None)
        blind = agent.method.deployed_context(unknown, mask, None)
        assert torch.isfinite(known).all()
        if reads:
            assert not torch.isfinite(blind).all()   # it did read the reward
        else:
            assert torch.equal(known, blind)
