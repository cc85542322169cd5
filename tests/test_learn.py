"""Pattern learning: reproducible, resumable, improves its loss, clear errors."""
import dataclasses
import json
import math
import shutil

import time
from pathlib import Path

import numpy as np
import pytest
import torch

import train.learn as learn
from capture_sim.errors import InputError
from capture_sim.rig import load_rig
from capture_sim.scene import save_scene
from capture_sim.synth import synthesize_scene
from patterns.families import make_patterns
from train.learn import TrainConfig, normal_loss, train_patterns


@pytest.fixture(scope="module")
def scene_dirs(tmp_path_factory):
    root = tmp_path_factory.mktemp("learn_scenes")
    rig = load_rig()
    for split, specs in {"train": [("sphere", "lambertian", 0), ("blob", "textured", 1)], "val": [("blob", "lambertian", 2)]}.items():
        for shape, material, seed in specs:
            save_scene(synthesize_scene(shape, material, rig, height=20, width=24, seed=seed), root / split / f"{shape}-{seed}.npz")
    return root / "train", root / "val"


def _config(scene_dirs, **changes):
    values = dict(num_patterns=3, steps=4, scenes=(str(scene_dirs[0]),), val_scenes=(str(scene_dirs[1]),), pixels_per_scene=64, checkpoint_every=2, val_every=2)
    values.update(changes)
    return TrainConfig(**values)


def test_same_seed_same_patterns_and_resume_matches(tmp_path, scene_dirs, monkeypatch):
    config = _config(scene_dirs)
    first = train_patterns(config, tmp_path / "a.npz", progress=False)
    second = train_patterns(config, tmp_path / "b.npz", progress=False)
    np.testing.assert_array_equal(first.patterns, second.patterns)

    original = learn.training_loss

    def interrupted(logits, scenes, cfg, step, ps_config):
        if step == 3:
            raise KeyboardInterrupt
        if step < 2:
            time.sleep(0.3)  # the interrupted session's time up to its checkpoint (step 2) must count
        return original(logits, scenes, cfg, step, ps_config)

    monkeypatch.setattr(learn, "training_loss", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train_patterns(config, tmp_path / "c.npz", progress=False)
    assert (tmp_path / "c.ckpt.pt").exists() and not (tmp_path / "c.npz").exists()
    monkeypatch.setattr(learn, "training_loss", original)
    resumed = train_patterns(config, tmp_path / "c.npz", progress=False)
    np.testing.assert_array_equal(first.patterns, resumed.patterns)
    assert resumed.seconds >= 0.6
    assert first.patterns.min() >= 0 and first.patterns.max() <= 1 and first.patterns.shape == (3, 9, 16, 3)
    assert [step for step, _ in first.val_history] == [2, 4]


def test_a_writer_sorts_after_an_event_file_of_its_own_second(tmp_path):
    """TensorBoard reads event files in name order (a resumed run's purge relies on it); a file of
    the same second may sort after the new one (its counter 9 after 10, another host name)."""
    earlier = tmp_path / f"events.out.tfevents.{int(time.time()):010d}.zzzz.1.9"
    earlier.write_bytes(b"")
    writer = learn.summary_writer(tmp_path, first_new_step=3)
    writer.close()
    names = sorted(path.name for path in tmp_path.glob("events.out.tfevents.*"))
    assert len(names) == 2 and names[0] == earlier.name


def test_tensorboard_log_of_a_resumed_run_has_each_step_once_with_the_rate_it_used(tmp_path, scene_dirs, monkeypatch):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    config = _config(scene_dirs, steps=6, checkpoint_every=2, val_every=0)
    original = learn.training_loss

    def interrupted(logits, scenes, cfg, step, ps_config):
        if step == 3:  # after logging step 3, with the checkpoint at step 2
            raise KeyboardInterrupt
        return original(logits, scenes, cfg, step, ps_config)

    monkeypatch.setattr(learn, "training_loss", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train_patterns(config, tmp_path / "p.npz", progress=False, logdir=tmp_path / "tb")
    monkeypatch.setattr(learn, "training_loss", original)
    train_patterns(config, tmp_path / "p.npz", progress=False, logdir=tmp_path / "tb")
    events = EventAccumulator(str(tmp_path / "tb"))
    events.Reload()
    assert [event.step for event in events.Scalars("train/loss")] == [1, 2, 3, 4, 5, 6]
    rates = [event.value for event in events.Scalars("train/learning_rate")]
    assert rates[0] == pytest.approx(config.learning_rate)  # step 1 uses the initial rate
    assert rates[-1] > config.learning_rate * config.final_lr_fraction * 1.0001  # the last step does not use the final rate yet
    # A fresh run into the same folder (another output) hides nothing of the runs there.
    train_patterns(dataclasses.replace(config, steps=2), tmp_path / "q.npz", progress=False, logdir=tmp_path / "tb")
    events = EventAccumulator(str(tmp_path / "tb"))
    events.Reload()
    assert len(events.Scalars("train/loss")) == 6 + 2


def test_a_checkpoint_that_cannot_be_written_is_one_error(tmp_path, scene_dirs, monkeypatch):
    """torch's zip writer reports a full disk as a RuntimeError ('unexpected pos ...'): it used to
    end the command in a traceback."""
    def full_disk(state, path):
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 2624 vs 2518")

    monkeypatch.setattr(learn.torch, "save", full_disk)
    with pytest.raises(InputError, match=r"cannot write checkpoint .*a.ckpt.pt.*is the disk full"):
        train_patterns(_config(scene_dirs, steps=2), tmp_path / "a.npz", progress=False)
    assert sorted(path.name for path in tmp_path.iterdir()) == []  # no temporary file left


def test_tensorboard_logs_both_terms_of_a_loss_with_re_rendering(tmp_path, scene_dirs):
    """With rerender_weight > 0 the summed loss and its two terms are logged: loss = normal + w rerender."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    config = _config(scene_dirs, steps=2, val_every=0, rerender_weight=0.5)
    train_patterns(config, tmp_path / "r.npz", progress=False, logdir=tmp_path / "tb")
    events = EventAccumulator(str(tmp_path / "tb"))
    events.Reload()
    total, normal, rendered = ([event.value for event in events.Scalars(f"train/{name}")] for name in ("loss", "normal_loss", "rerender_loss"))
    assert len(total) == len(normal) == len(rendered) == 2
    assert np.allclose(total, np.asarray(normal) + 0.5 * np.asarray(rendered), rtol=1e-5)


def test_learning_lowers_training_loss(scene_dirs):
    config = _config(scene_dirs, steps=0, init="tri_random")
    rig = load_rig()
    from train.scene_pixels import scene_pixels
    from train.scene_sets import resolve_scenes
    from patterns.families import make_patterns
    from patterns.parameterization import patterns_to_logits
    from reconstruct.unrolled_ps import UnrolledPSConfig

    scenes = learn.training_samplers([scene_pixels(s, rig, True) for s in resolve_scenes(config.scenes, "train", rig)], config)
    logits = patterns_to_logits(make_patterns("tri_random", 3)).requires_grad_()
    optimiser = torch.optim.Adam([logits], lr=0.1)
    losses = []
    for step in range(15):
        optimiser.zero_grad()
        # The same pixels and noise every step, so the loss curve reflects the patterns alone.
        loss = learn.training_loss(logits, scenes, config, 0, UnrolledPSConfig())
        loss.backward()
        optimiser.step()
        losses.append(float(loss.detach()))
        assert torch.isfinite(logits.grad).all()
    assert losses[-1] < losses[0]


def test_capped_loss_with_a_cap_beyond_float32_is_the_angular_loss():
    """A cap of 180 degrees or more caps nothing; 1e300 used to overflow float32."""
    estimate = torch.nn.functional.normalize(torch.randn(6, 3), dim=1)
    truth = torch.nn.functional.normalize(torch.randn(6, 3), dim=1)
    angular = normal_loss(estimate, truth, "angular")
    for cap in (180.0, 1e300, math.inf):
        assert torch.equal(normal_loss(estimate, truth, "capped_angular", cap), angular)
    assert float(normal_loss(estimate.numpy(), truth.numpy(), "cosine")) == pytest.approx(float(normal_loss(estimate, truth, "cosine")))
    # A noise scale beyond MAX_NOISE_SCALE fails when the config is made, not at the first capture.
    with pytest.raises(InputError, match="noise_scale must be a number in"):
        TrainConfig(noise_scale=1e17)
    # Bad input raises instead of a NaN loss or a silent fallback to another kind.
    for args in ((estimate, truth, "angualr"), (estimate[:0], truth[:0], "angular"), (estimate, truth[0], "angular"),
                 (estimate, truth, "capped_angular", math.nan)):
        with pytest.raises(InputError):
            normal_loss(*args)


def test_normal_loss_is_finite_at_exact_match():
    normal = torch.tensor([[0.0, 0.0, -1.0]], requires_grad=True)
    loss = normal_loss(normal, normal.detach().clone(), "angular")
    loss.backward()
    assert float(loss.detach()) < 1e-2 and torch.isfinite(normal.grad).all()


def test_capped_angular_loss_ignores_only_pixels_beyond_the_cap():
    truth = torch.tensor([[0.0, 0.0, -1.0]] * 3, dtype=torch.float64)
    tilt = torch.tensor([10.0, 30.0, 60.0], dtype=torch.float64).deg2rad()  # the last is beyond 40 deg
    estimate = torch.stack([torch.sin(tilt), torch.zeros(3, dtype=torch.float64), -torch.cos(tilt)], dim=1).requires_grad_()
    capped = normal_loss(estimate, truth, "capped_angular", 40.0)
    torch.testing.assert_close(capped, torch.tensor([10.0, 30.0, 40.0], dtype=torch.float64).deg2rad().mean())
    capped.backward()
    assert estimate.grad[:2].abs().sum(1).gt(0).all() and not estimate.grad[2].any()
    torch.testing.assert_close(normal_loss(estimate, truth, "capped_angular"), capped)  # the default cap is TrainConfig's
    torch.testing.assert_close(normal_loss(estimate, truth, "capped_angular", math.inf), normal_loss(estimate, truth, "angular"))
    with pytest.raises(InputError, match="angle_cap_deg"):
        TrainConfig(angle_cap_deg=0.0)
    TrainConfig(loss="angular", angle_cap_deg=0.0)  # unused by the other losses
    with pytest.raises(InputError, match="angle_cap_deg"):
        TrainConfig(loss="angular", angle_cap_deg=math.nan)  # but refused there too, not at the first step
    # A learning rate whose Adam step would overflow float32 (a traceback inside torch) is refused.
    for rate in (1e39, math.inf, math.nan, 0.0):
        with pytest.raises(InputError, match="learning_rate must be a number in"):
            TrainConfig(learning_rate=rate)


def test_damaged_or_foreign_checkpoints_are_refused(tmp_path, scene_dirs):
    config = _config(scene_dirs, steps=2, val_every=0)
    train_patterns(config, tmp_path / "a.npz", progress=False)
    checkpoint = (tmp_path / "a.ckpt.pt").read_bytes()
    for name, content in (("truncated", checkpoint[: len(checkpoint) // 2]), ("text", b"not a checkpoint\n")):
        (tmp_path / f"{name}.ckpt.pt").write_bytes(content)
        with pytest.raises(InputError, match="damaged or not a torch checkpoint"):
            train_patterns(config, tmp_path / f"{name}.npz", progress=False)
    torch.save({"logits": torch.zeros(3)}, tmp_path / "foreign.ckpt.pt")
    with pytest.raises(InputError, match="not a displex training checkpoint"):
        train_patterns(config, tmp_path / "foreign.npz", progress=False)
    # The config kept but the patterns or the optimiser edited: one line, not a RuntimeError in copy_.
    state = torch.load(tmp_path / "a.ckpt.pt", weights_only=True)
    for name, edit, what in (("other_m", {"logits": state["logits"][:1]}, "its patterns"), ("nan", {"logits": state["logits"] * math.nan}, "its patterns"),
                             ("optimiser", {"optimiser": {"state": {}, "param_groups": []}}, "its optimiser state"),
                             ("moments", {"optimiser": {**state["optimiser"], "state": {0: {**state["optimiser"]["state"][0], "exp_avg": torch.zeros(5)}}}},
                              "its optimiser state"),  # Adam loads it, then fails in its first step
                             ("nan_moments", {"optimiser": {**state["optimiser"], "state": {0: {**state["optimiser"]["state"][0],
                                                                                                "exp_avg_sq": state["logits"] * math.nan}}}}, "its optimiser state")):
        torch.save({**state, **edit}, tmp_path / f"{name}.ckpt.pt")
        with pytest.raises(InputError, match=f"is damaged: {what} do(es)? not fit its config"):
            train_patterns(config, tmp_path / f"{name}.npz", progress=False)
    longer = _config(scene_dirs, steps=3, val_every=0)
    with pytest.raises(InputError, match=r"another config \(steps differ\); pass --fresh"):
        train_patterns(longer, tmp_path / "a.npz", progress=False)
    # A caller that owns the folder replaces a stale or damaged checkpoint; --fresh deletes any.
    replaced = train_patterns(longer, tmp_path / "truncated.npz", progress=False, checkpoint_mode="resume_or_fresh")
    afresh = train_patterns(longer, tmp_path / "a.npz", progress=False, checkpoint_mode="fresh")
    assert np.array_equal(replaced.patterns, afresh.patterns)
    with pytest.raises(InputError, match="checkpoint_mode"):
        train_patterns(config, tmp_path / "a.npz", progress=False, checkpoint_mode="maybe")


def test_a_stale_checkpoint_is_refused_before_the_scenes_are_read(tmp_path, scene_dirs, monkeypatch):
    config = _config(scene_dirs, steps=2, val_every=0)
    train_patterns(config, tmp_path / "a.npz", progress=False)
    checkpoint = (tmp_path / "a.ckpt.pt").read_bytes()
    read = []
    real_resolve = learn.resolve_scenes
    monkeypatch.setattr(learn, "resolve_scenes", lambda *args, **kwargs: read.append(args[1]) or real_resolve(*args, **kwargs))
    # Default scenes would be synthesised first: a refusal must not wait for them.
    with pytest.raises(InputError, match=r"another config \(steps differ\)"):
        train_patterns(_config(scene_dirs, steps=3, val_every=0), tmp_path / "a.npz", progress=False)
    assert read == []
    # --fresh deletes the checkpoint only once the scenes have loaded: bad scenes leave it.
    monkeypatch.setattr(learn, "resolve_scenes", lambda *args, **kwargs: (_ for _ in ()).throw(InputError("no such scene")))
    with pytest.raises(InputError, match="no such scene"):
        train_patterns(_config(scene_dirs, steps=3, val_every=0), tmp_path / "a.npz", progress=False, checkpoint_mode="fresh")
    assert (tmp_path / "a.ckpt.pt").read_bytes() == checkpoint


def test_a_broken_link_in_a_scene_folder_is_one_error(tmp_path, scene_dirs):
    folder = tmp_path / "scenes"
    shutil.copytree(scene_dirs[0], folder)
    (folder / "zz-broken.npz").symlink_to(tmp_path / "nonexistent.npz")
    with pytest.raises(InputError, match="not found: .*zz-broken.npz"):
        train_patterns(_config(scene_dirs, scenes=(str(folder),)), tmp_path / "a.npz", progress=False)


def test_checkpoint_of_scene_files_rewritten_since_is_refused(tmp_path, scene_dirs):
    """A finished or interrupted run made from scene files that were rewritten since neither resumes
    on them nor reports its old validation as theirs."""
    copies = [tmp_path / folder.name for folder in scene_dirs]
    for folder, copy in zip(scene_dirs, copies):
        shutil.copytree(folder, copy)
    config = _config(copies, steps=2, val_every=0)
    train_patterns(config, tmp_path / "a.npz", progress=False)
    train_patterns(config, tmp_path / "a.npz", progress=False)  # unchanged files: the finished run is reused
    rewritten = sorted(copies[1].glob("*.npz"))[0]
    rewritten.write_bytes(rewritten.read_bytes())  # same content, written again: its files may differ
    with pytest.raises(InputError, match=rf"made from input files \(scenes, start patterns, rig\) that were rewritten, replaced or touched since \({rewritten.name}\); pass --fresh"):
        train_patterns(config, tmp_path / "a.npz", progress=False)


def test_checkpoint_resumes_with_scenes_named_relative_or_absolute(tmp_path, scene_dirs, monkeypatch):
    monkeypatch.chdir(scene_dirs[0].parent)
    absolute = _config(scene_dirs, steps=2, val_every=0)
    relative = _config(scene_dirs, steps=2, val_every=0, scenes=("train",), val_scenes=("./val",))
    train_patterns(absolute, tmp_path / "a.npz", progress=False)
    calls = []
    monkeypatch.setattr(learn, "training_loss", lambda *args: calls.append(args) or torch.zeros(()))
    resumed = train_patterns(relative, tmp_path / "a.npz", progress=False)  # finished: nothing left to run
    assert not calls and resumed.patterns.shape == (3, 9, 16, 3)
    assert json.loads((tmp_path / "a.config.json").read_text())["scenes"] == ["train"]  # the record keeps names as given
    # The same relative name from another folder means other files: refused, not resumed.
    monkeypatch.chdir(tmp_path)
    for folder in scene_dirs:
        shutil.copytree(folder, tmp_path / folder.name)
    with pytest.raises(InputError, match=r"another config \(input_files, scenes, val_scenes differ\)"):
        train_patterns(relative, tmp_path / "a.npz", progress=False)


def test_bad_config_raises(tmp_path, scene_dirs):
    with pytest.raises(InputError, match="init"):
        train_patterns(_config(scene_dirs, init="no_such_family"), tmp_path / "x.npz", progress=False)
    with pytest.raises(InputError):
        TrainConfig(loss="l7")
    with pytest.raises(InputError):
        TrainConfig(num_patterns=0)
    for bad in (dict(checkpoint_every=0), dict(val_every=-1), dict(seed=-1), dict(init="no_such_family")):
        with pytest.raises(InputError):
            TrainConfig(**bad)


def test_config_files_are_type_checked(tmp_path):
    from train.config_io import load_config

    for body in ("scene_size = 24", "scene_size = [128]", 'scene_size = [128, "153"]', 'steps = "two"', 'scenes = "one/folder"', "scenes = [1, 2]", "learning_rate = true"):
        path = tmp_path / "c.toml"
        path.write_text(body + "\n")
        with pytest.raises(InputError):
            load_config(TrainConfig, path)
    path.write_text("learning_rate = 2\n")  # an integer is a fine float
    assert load_config(TrainConfig, path).learning_rate == 2


def test_paths_in_config_files_are_relative_to_the_folder_holding_configs(tmp_path, monkeypatch):
    """As in compare configs, whatever the working directory; flags stay relative to it."""
    from train.config_io import load_config
    from train.search import SearchConfig

    (tmp_path / "proj" / "configs" / "train").mkdir(parents=True)
    (tmp_path / "loose").mkdir()
    body = 'rig = "rigs/mine.toml"\nscenes = ["data/a.npz", "/abs/b"]\nval_scenes = ["data/v"]\ninit = "p/start.npz"\nscene_size = [8, 10]\n'
    (tmp_path / "proj" / "configs" / "train" / "t.toml").write_text(body)
    (tmp_path / "loose" / "t.toml").write_text(body)
    monkeypatch.chdir(tmp_path / "loose")
    for config_path, root in ((tmp_path / "proj" / "configs" / "train" / "t.toml", tmp_path / "proj"), (Path("t.toml"), tmp_path / "loose")):
        config = load_config(TrainConfig, config_path)
        assert config.rig == str(root / "rigs" / "mine.toml") and config.init == str(root / "p" / "start.npz")
        assert config.scenes == (str(root / "data" / "a.npz"), "/abs/b") and config.val_scenes == (str(root / "data" / "v"),)
    assert load_config(TrainConfig, config_path, {"scenes": ("x",)}).scenes == ("x",)  # a flag's path is the working directory's
    (tmp_path / "loose" / "s.toml").write_text('rig = "dir-odyssey-ark"\nscenes = ["s"]\n')
    config = load_config(SearchConfig, tmp_path / "loose" / "s.toml")
    assert config.rig == "dir-odyssey-ark" and config.scenes == (str(tmp_path / "loose" / "s"),)  # a preset name stays a name


def test_user_scenes_without_val_scenes_are_not_validated_and_reruns_keep_the_loss(tmp_path, scene_dirs):
    import json

    from patterns.io import load_patterns

    config = _config(scene_dirs, val_scenes=())
    result = train_patterns(config, tmp_path / "a.npz", progress=False)
    assert result.val_history == []
    # Running the finished command again rewrites the same patterns with the same final loss.
    again = train_patterns(config, tmp_path / "a.npz", progress=False)
    np.testing.assert_array_equal(result.patterns, again.patterns)
    _, meta = load_patterns(tmp_path / "a.npz")
    assert meta["final_train_loss"] == pytest.approx(result.final_loss) and math.isfinite(meta["final_train_loss"])
    json.dumps(meta, allow_nan=False)


def test_shuffled_windows_are_views_of_every_pixel(scene_dirs):
    from train.scene_pixels import scene_pixels, shuffle_pixels
    from train.scene_sets import resolve_scenes

    rig = load_rig()
    pixels = scene_pixels(resolve_scenes((str(scene_dirs[0]),), "train", rig)[0], rig, True)
    sampler = shuffle_pixels(pixels, 50, torch.Generator().manual_seed(3))
    shuffled = sampler.scene
    assert shuffled.num_pixels == pixels.num_pixels + 49 and sampler.reach.shape == (rig.num_lights, pixels.num_pixels + 49)
    # The order is a permutation of every pixel, wrapped by window - 1.
    order = shuffled.transport.pixel_index
    assert sorted(order[: pixels.num_pixels].tolist()) == sorted(pixels.transport.pixel_index.tolist())
    assert torch.equal(order[pixels.num_pixels:], order[:49])
    generator = torch.Generator().manual_seed(0)
    for _ in range(20):
        part = sampler.draw(generator)
        window = shuffled.transport.subset(part).matrix
        assert window.shape[2] == 50 and window.untyped_storage().data_ptr() == shuffled.transport.matrix.untyped_storage().data_ptr()
    # Auto exposure over the shuffled copy's distinct pixels equals the one over the source scene.
    from train.capture import scene_exposure

    patterns = make_patterns("mono_gradient", 4).float()
    every = sampler.every_pixel()
    assert every.num_pixels == pixels.num_pixels and every.points.shape == pixels.points.shape
    assert scene_exposure(every, patterns) == pytest.approx(scene_exposure(pixels, patterns), rel=1e-6)
    with pytest.raises(InputError):
        shuffle_pixels(pixels, 0, generator)


def test_default_toml_agrees_with_train_config():
    from pathlib import Path

    from train.config_io import load_config

    path = Path(__file__).resolve().parents[1] / "configs" / "train" / "default.toml"
    assert load_config(TrainConfig, path) == TrainConfig()


def test_full_solver_loss_has_finite_gradients(scene_dirs):
    from patterns.families import make_patterns
    from patterns.parameterization import patterns_to_logits
    from reconstruct.unrolled_ps import UnrolledPSConfig
    from train.scene_pixels import scene_pixels
    from train.scene_sets import resolve_scenes

    with pytest.raises(InputError, match="solver"):
        TrainConfig(solver="newton")
    config = _config(scene_dirs, solver="full")
    rig = load_rig()
    scenes = learn.training_samplers([scene_pixels(s, rig, True) for s in resolve_scenes(config.scenes, "train", rig)], config)
    logits = patterns_to_logits(make_patterns("tri_random", 3)).requires_grad_()
    loss = learn.training_loss(logits, scenes, config, 0, UnrolledPSConfig())
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(logits.grad).all() and float(logits.grad.abs().sum()) > 0


@pytest.mark.parametrize("solver", ["unrolled", "full"])
def test_joint_solve_of_scenes_equals_solving_each_scene(scene_dirs, solver):
    """One solve for all training scenes (each captured at its own exposure) gives each scene's
    normals, and albedo rescaled to the scene's own exposure, as solving the scenes one by one."""
    from reconstruct.unrolled_ps import UnrolledPSConfig
    from train.capture import capture_scene, scene_exposure
    from train.scene_pixels import scene_pixels
    from train.scene_sets import resolve_scenes

    rig = load_rig()
    config = _config(scene_dirs, solver=solver)
    samplers = learn.training_samplers([scene_pixels(s, rig, True) for s in resolve_scenes(config.scenes, "train", rig)], config)
    patterns = make_patterns("tri_random", 3, seed=1).double()
    generator = torch.Generator().manual_seed(0)
    draws = []
    for sampler, exposure_scale in zip(samplers, (1.0, 0.2)):  # very different exposures
        part = sampler.draw(generator)
        exposure = exposure_scale * scene_exposure(sampler.every_pixel(), patterns)
        draws.append((sampler, part, capture_scene(sampler.scene, patterns, 0.0, exposure, generator, part)))
    joint = learn.reconstruct_draws(draws, solver, UnrolledPSConfig())
    for draw, (normal, albedo) in zip(draws, joint):
        alone_normal, alone_albedo = learn.reconstruct_draws([draw], solver, UnrolledPSConfig())[0]
        assert normal.shape == (draw[2].captures.shape[1], 3)
        torch.testing.assert_close(normal, alone_normal, atol=1e-6, rtol=0)
        torch.testing.assert_close(albedo, alone_albedo, atol=1e-6, rtol=1e-5)


def test_logits_stay_movable_even_with_huge_steps(tmp_path, scene_dirs):
    from patterns.parameterization import LOGIT_LIMIT

    config = _config(scene_dirs, learning_rate=50.0, steps=3, checkpoint_every=3, val_every=0)
    train_patterns(config, tmp_path / "big.npz", progress=False)
    logits = torch.load(tmp_path / "big.ckpt.pt", weights_only=True)["logits"]
    assert float(logits.abs().max()) <= LOGIT_LIMIT
    # Every value keeps a non-zero gradient through the sigmoid.
    values = logits.clone().requires_grad_(True)
    torch.sigmoid(values).sum().backward()
    assert bool((values.grad > 0).all())


def test_zero_steps_validate_the_start_patterns(scene_dirs, tmp_path):
    """With no step to validate after, the start patterns are validated once (the command used to
    say 'not validated: pass --val-scenes' to a user who had passed it)."""
    result = learn.train_patterns(_config(scene_dirs, steps=0, init="tri_random"), tmp_path / "p.npz", progress=False)
    assert [step for step, _ in result.val_history] == [0] and math.isfinite(result.val_history[0][1])


@pytest.mark.parametrize("kind", ["angular", "capped_angular", "cosine"])
def test_normal_loss_closed_form_and_gradcheck(kind):
    truth = torch.tensor([[0.0, 0.0, -1.0]] * 3, dtype=torch.float64)
    tilt = torch.tensor([10.0, 30.0, 60.0], dtype=torch.float64).deg2rad()
    estimate = torch.stack([torch.sin(tilt), torch.zeros(3, dtype=torch.float64), -torch.cos(tilt)], 1)
    expected = {"angular": tilt.mean(), "capped_angular": tilt.clamp_max(math.radians(40)).mean(), "cosine": (1 - torch.cos(tilt)).mean()}[kind]
    torch.testing.assert_close(normal_loss(estimate, truth, kind), expected)
    probe = torch.randn(4, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    probe = probe / probe.norm(dim=1, keepdim=True)
    probe[:, 2] = -probe[:, 2].abs()
    assert torch.autograd.gradcheck(lambda e: normal_loss(e, truth[:1].expand(4, 3), kind, 80.0), (probe.requires_grad_(),))


def test_a_second_run_on_the_same_output_is_refused(tmp_path, scene_dirs):
    """Two runs writing one --out at once would share a checkpoint: the second fails at once."""
    from capture_sim.atomic import exclusive_output

    out = tmp_path / "a.npz"
    config = _config(scene_dirs, steps=1, val_every=0)
    with exclusive_output(out, "training run"):
        with pytest.raises(InputError, match=f"another training run is writing {out} right now"):
            train_patterns(config, out, progress=False)
        # a.NPZ's checkpoint and config record would be a.npz's (they are named by the stem).
        with pytest.raises(InputError, match="right now"):
            train_patterns(config, tmp_path / "a.NPZ", progress=False)
    assert not (tmp_path / ".a.lock").exists()
    train_patterns(config, out, progress=False)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["a.ckpt.pt", "a.config.json", "a.npz"]
    # A run refused after taking the lock (here its start file) leaves no output folder it made.
    nested = tmp_path / "new" / "folder" / "b.npz"
    with pytest.raises(InputError, match="missing.npz"):
        train_patterns(dataclasses.replace(config, init=str(tmp_path / "missing.npz")), nested, progress=False)
    assert not (tmp_path / "new").exists()
    with pytest.raises(InputError, match="File name too long"):  # the output's name is legal, its lock's is not
        with exclusive_output(tmp_path / "new" / "folder" / ("a" * 251 + ".npz"), "training run"):
            pass
    assert not (tmp_path / "new").exists()


def test_the_output_lock_and_the_final_moves_survive_races_and_interrupts(tmp_path, monkeypatch, python_sigint):
    """A run that opened the lock file just before its holder removed it must not keep a lock on
    the removed file (a third run could lock a new one beside it); SIGINT and SIGTERM during the
    moves of staged outputs arrive after them and after the clean-up, SIGTERM first."""
    import builtins
    import os
    import signal

    from capture_sim.atomic import exclusive_output, staged_files

    out = tmp_path / "a.npz"
    lock = tmp_path / ".a.lock"
    opened = []

    def open_then_lose_the_race(path, *args, **kwargs):
        handle = builtins.open(path, *args, **kwargs)
        if not opened:  # the holder removes the file between this open and the lock
            os.unlink(path)
        opened.append(path)
        return handle

    monkeypatch.setattr("capture_sim.atomic.open", open_then_lose_the_race, raising=False)
    with exclusive_output(out, "training run"):
        monkeypatch.undo()
        assert len(opened) == 2 and lock.exists()  # locked the file that stands there now
        with pytest.raises(InputError, match="another training run is writing"):
            with exclusive_output(out, "training run"):
                pass

    replace, received = os.replace, []

    def interrupted_replace(source, target):
        replace(source, target)
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr("capture_sim.atomic.os.replace", interrupted_replace)
    previous = signal.signal(signal.SIGTERM, lambda number, _frame: received.append(number))
    try:
        with pytest.raises(KeyboardInterrupt):
            with staged_files(tmp_path / "out") as staging:
                (staging / "a.txt").write_text("a")
                (staging / "b.txt").write_text("b")
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert sorted(path.name for path in (tmp_path / "out").iterdir()) == ["a.txt", "b.txt"]  # no staging folder
    assert received == [signal.SIGTERM]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_train_writes_its_pattern_file_and_config_record_together(tmp_path, scene_dirs, monkeypatch):
    """A stop while the outputs are written leaves the earlier run's pair, not a new pattern file
    beside the earlier record."""
    out = tmp_path / "a.npz"
    config = _config(scene_dirs, steps=1, val_every=0)
    train_patterns(config, out, progress=False)
    before = {path.name: path.read_bytes() for path in (out, tmp_path / "a.config.json")}
    write_json = __import__("train.learn", fromlist=["write_json"]).write_json

    def stopped(path, *args, **kwargs):
        if str(path).endswith(".config.json"):
            raise KeyboardInterrupt
        return write_json(path, *args, **kwargs)

    monkeypatch.setattr("train.learn.write_json", stopped)
    with pytest.raises(KeyboardInterrupt):
        train_patterns(dataclasses.replace(config, steps=2), out, progress=False, checkpoint_mode="fresh")
    assert {path.name: path.read_bytes() for path in (out, tmp_path / "a.config.json")} == before


def test_held_signals_are_all_restored_when_a_restored_handler_raises(monkeypatch):
    """A SIGTERM whose restored handler raises (sys.exit) while the handlers are put back must not
    leave SIGINT held for good."""
    import signal

    from capture_sim.atomic import signals_held

    original = signal.signal

    def set_then_raise(number, handler):
        previous = original(number, handler)
        if number == signal.SIGTERM and handler is signal.SIG_DFL:  # the restore, then a signal arrives
            raise SystemExit(143)
        return previous

    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(SystemExit):
        with signals_held():
            monkeypatch.setattr(signal, "signal", set_then_raise)
    monkeypatch.undo()
    assert signal.getsignal(signal.SIGINT) is before


def test_training_scenes_are_prepared_one_at_a_time(scene_dirs):
    """Every training scene was held twice (unshuffled and shuffled) and its loaded arrays a third
    time until all were shuffled: `train --steps 1` on three full-resolution scenes 4.6 GB, now 3.5. The loaded
    scenes and unshuffled pixels must be released as the samplers are made, with the same samplers."""
    import gc
    import weakref

    from train.scene_pixels import scene_pixels
    from train.scene_sets import resolve_scenes

    rig = load_rig()
    config = _config(scene_dirs)
    expected = learn.training_samplers([scene_pixels(s, rig, True) for s in resolve_scenes(config.scenes, "train", rig)], config)
    scenes = resolve_scenes(config.scenes, "train", rig)
    loaded = [weakref.ref(scene) for scene in scenes]
    released = []

    def watched():
        for pixels in learn.prepared_scenes(scenes, rig):
            prepared = weakref.ref(pixels)
            yield pixels
            del pixels
            gc.collect()  # resumed for the next scene: this one's shuffled copy is made
            released.append((prepared() is None, loaded[len(released)]() is None))

    samplers = learn.training_samplers(watched(), config)
    assert scenes == [] and len(samplers) == len(expected) == len(loaded) >= 2
    assert released[:-1] == [(True, True)] * (len(loaded) - 1), "a scene outlived its shuffled copy"
    for sampler, reference in zip(samplers, expected):
        assert torch.equal(sampler.scene.transport.matrix, reference.scene.transport.matrix) and torch.equal(sampler.reach, reference.reach)
