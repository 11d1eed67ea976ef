"""drsplat.features.clip: loading through the real open_clip path (random-weight checkpoints), text cache,
normalisation, model ids, and clear errors when weights are missing."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from drsplat.errors import DrsplatError, InputError, WeightsUnavailableError
from drsplat.features.clip import ClipEncoder
from drsplat.features.modelid import CANONICAL_PHRASES, check_compatible
from drsplat.features.weights import resolve_pretrained_weights

TINY_CLIP = "TinyCLIP-drsplat-test"
TINY_CFG = {
    "embed_dim": 32,
    "vision_cfg": {"image_size": 224, "layers": 1, "width": 32, "patch_size": 32, "head_width": 16},
    "text_cfg": {"context_length": 77, "vocab_size": 49408, "width": 32, "heads": 2, "layers": 1},
}
OFFLINE_CLIP_MESSAGE = (
    "OpenCLIP weights for ViT-B-16 (laion2b_s34b_b88k) are not in the local cache and cannot be downloaded; "
    "pass --clip-checkpoint PATH to a local open_clip checkpoint, or run once with internet access."
)


def make_tiny_clip(folder: Path, seed: int = 0) -> Path:
    """Register a tiny open_clip architecture and save random weights for it; returns the file."""
    import open_clip

    folder.mkdir(parents=True, exist_ok=True)
    cfg = folder / f"{TINY_CLIP}.json"
    cfg.write_text(json.dumps(TINY_CFG))
    open_clip.add_model_config(cfg)
    torch.manual_seed(seed)
    ckpt = folder / "tiny_clip.pt"
    torch.save(open_clip.create_model(TINY_CLIP).state_dict(), ckpt)
    return ckpt


@pytest.fixture(scope="module")
def tiny_clip(tmp_path_factory) -> Path:
    return make_tiny_clip(tmp_path_factory.mktemp("clip"))


@pytest.fixture(scope="module")
def encoder(tiny_clip) -> ClipEncoder:
    return ClipEncoder(TINY_CLIP, checkpoint=tiny_clip, device="cpu", batch_size=3)


def test_checkpoint_loads_the_saved_weights(tiny_clip, encoder):
    state = torch.load(tiny_clip, weights_only=True)
    for name, value in encoder.net.state_dict().items():
        assert torch.equal(value, state[name]), name
    assert encoder.model_id == f"{TINY_CLIP}/file:tiny_clip.pt"
    assert encoder.dim == 32 and encoder.image_size == 224


def test_pretrained_label_names_a_checkpoint(tiny_clip):
    enc = ClipEncoder(TINY_CLIP, pretrained="my-finetune", checkpoint=tiny_clip, device="cpu")
    assert enc.model_id == f"{TINY_CLIP}/my-finetune"


def test_encode_images_applies_clip_normalisation_in_batches(encoder):
    rng = np.random.default_rng(0)
    images = rng.random((7, 3, 224, 224)).astype(np.float32)  # 7 = 3 batches of 3
    got = encoder.encode_images(images)
    mean = torch.tensor(encoder.mean).view(1, 3, 1, 1)
    std = torch.tensor(encoder.std).view(1, 3, 1, 1)
    with torch.no_grad():
        ref = encoder.net.encode_image((torch.from_numpy(images) - mean) / std)
    ref = torch.nn.functional.normalize(ref, dim=-1).numpy()
    assert got.dtype == np.float32 and got.shape == (7, 32)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(got, ref, atol=1e-5)


def test_text_embeddings_are_cached_per_phrase(tiny_clip):
    enc = ClipEncoder(TINY_CLIP, checkpoint=tiny_clip, device="cpu")
    seen: list[int] = []
    original = enc.net.encode_text

    def counting(tokens, *a, **k):
        seen.append(tokens.shape[0])
        return original(tokens, *a, **k)

    enc.net.encode_text = counting
    first = enc.encode_text(["a fern", "a leaf", "a fern"])
    second = enc.encode_text(["a leaf", "a pot"])
    assert seen == [2, 1]  # "a fern", "a leaf" once; then only "a pot"
    np.testing.assert_array_equal(first[0], first[2])
    np.testing.assert_array_equal(first[1], second[0])
    np.testing.assert_allclose(np.linalg.norm(second, axis=1), 1.0, atol=1e-5)
    canon = enc.canonical_embeddings()
    assert CANONICAL_PHRASES == ("object", "things", "stuff", "texture")
    np.testing.assert_array_equal(canon, enc.encode_text(list(CANONICAL_PHRASES)))


def test_a_phrase_past_the_text_context_is_embedded_cut_and_said(encoder, caplog):
    """Round 61a: a phrase longer than CLIP's 77 tokens was cut without a word, so twelve phrases and
    'mug' scored exactly as the twelve alone. The cut is what CLIP does; it is now said, once a phrase."""
    limit = encoder.tokenizer.context_length
    long = " ".join(["the big red ball on the wooden table"] * 12)
    assert len(encoder.tokenizer.encode(long)) + 2 > limit
    with caplog.at_level("WARNING", logger="drsplat.features.clip"):
        fits = encoder.encode_text(["a mug"])
        assert caplog.text == ""
        cut = encoder.encode_text([long + " mug", long + " astronaut"])
    np.testing.assert_array_equal(cut[0], cut[1])  # what the words past the context change: nothing
    assert caplog.text.count(f"more than the {limit} of") == 2 and f"only its first {limit - 2} are embedded" in caplog.text
    assert not np.array_equal(fits[0], cut[0])


@pytest.mark.parametrize("known", ["one way", "two ways", "none"])
def test_a_checkpoint_without_a_tag_is_normalised_as_its_models_weights_are(tiny_clip, monkeypatch, known):
    """Round 61c: a --clip-checkpoint given without --pretrained was normalised with OpenAI's mean and std whatever
    its model (a SigLIP one: cosine 0.85 to the right embedding of the same crops). Now as every known tag of the
    model does; a model whose tags disagree (ViT-L-14) is refused for images until --pretrained names the weights."""
    import open_clip

    tags = {"one way": {"a": (0.5, 0.5), "b": (0.5, 0.5)}, "two ways": {"openai": (None, None), "laion": (0.5, 0.5)}, "none": {}}[known]
    monkeypatch.setattr(open_clip, "list_pretrained_tags_by_model", lambda model: list(tags) if model == TINY_CLIP else [])
    monkeypatch.setattr(open_clip, "get_pretrained_cfg", lambda model, tag: {} if tags.get(tag, (None,))[0] is None else
                        {"mean": (tags[tag][0],) * 3, "std": (tags[tag][1],) * 3})  # {} for a tag it does not know, as open_clip
    enc = ClipEncoder(TINY_CLIP, checkpoint=tiny_clip, device="cpu")
    crops = np.random.default_rng(0).uniform(size=(2, 3, enc.image_size, enc.image_size)).astype(np.float32)
    assert enc.encode_text(["a fern"]).shape[0] == 1  # text needs no image normalisation
    if known == "two ways":
        with pytest.raises(InputError, match="normalise images in 2 ways .*pass --pretrained TAG"):
            enc.encode_images(crops)
        tagged = ClipEncoder(TINY_CLIP, pretrained="laion", checkpoint=tiny_clip, device="cpu")
        assert tagged.mean == (0.5,) * 3 and tagged.encode_images(crops).shape[0] == 2
        typo = ClipEncoder(TINY_CLIP, pretrained="laio", checkpoint=tiny_clip, device="cpu")  # round 62b: OpenAI's, silently
        with pytest.raises(InputError, match="normalise images in 2 ways"):
            typo.encode_images(crops)
        return
    assert enc.mean == ((0.5,) * 3 if known == "one way" else (0.48145466, 0.4578275, 0.40821073))
    assert enc.encode_images(crops).shape[0] == 2


def test_clip_configs_open_clip_would_fail_on_are_one_sentence_or_work(tmp_path):
    """Round 61c: three --clip-config cases ended in tracebacks: a folder holding one malformed .json (JSONDecodeError
    from open_clip), a text tower with "proj_bias": true (its projection an nn.Linear: AttributeError in `dim`),
    a rectangular image_size (a torch shape error at the first crops). Now: one error naming the file, the right D,
    one error saying crops are square."""
    import open_clip

    from drsplat.features.clip import use_clip_config

    folder = tmp_path / "configs"
    folder.mkdir()
    (folder / "Good.json").write_text(json.dumps(TINY_CFG))
    (folder / "Broken.json").write_text('{"embed_dim": 32,')
    with pytest.raises(InputError, match="Broken.json"):
        use_clip_config(folder)
    (folder / "Broken.json").unlink()
    (folder / "open_clip_config.json").write_text('{"model_cfg": {}}')  # other JSON beside the config: open_clip skips it (round 62b)
    use_clip_config(folder)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="holds no open_clip model config"):
        use_clip_config(tmp_path / "empty")
    biased = tmp_path / "TinyBias-drsplat-test.json"
    biased.write_text(json.dumps({**TINY_CFG, "text_cfg": {**TINY_CFG["text_cfg"], "proj_bias": True}}))
    use_clip_config(biased)
    enc = ClipEncoder("TinyBias-drsplat-test", None, None, "cpu", random_weights=True)
    assert isinstance(enc.net.text_projection, torch.nn.Linear) and enc.dim == 32 == enc.encode_text(["a"]).shape[1]
    rect = tmp_path / "TinyRect-drsplat-test.json"
    rect.write_text(json.dumps({**TINY_CFG, "vision_cfg": {**TINY_CFG["vision_cfg"], "image_size": [224, 160]}}))
    open_clip.add_model_config(rect)
    with pytest.raises(DrsplatError, match="takes 224x160 images; drsplat embeds square mask crops"):
        ClipEncoder("TinyRect-drsplat-test", None, None, "cpu", random_weights=True)


def test_a_model_named_in_another_case_is_built_as_open_clip_spells_it(tmp_path, tiny_clip, capsys):
    """Round 83a F2: model ids compare case-insensitively, so a field of 'vit-b-16:LAION2B_S34B_B88K' passed the model
    check, but open_clip's lookups are exact and the query was refused as an "unknown OpenCLIP model" needing
    --clip-config. The architecture is now built as open_clip spells it; a query of such a field runs."""
    from drsplat.cli import main
    from drsplat.lang import attach_field, build_field
    from drsplat.scene import save_ply
    from tests.test_index import tiny_scene

    encoder = ClipEncoder(TINY_CLIP.lower(), checkpoint=tiny_clip, device="cpu")
    assert encoder.model_name == TINY_CLIP
    field = build_field(np.eye(4, 32, dtype=np.float32), np.ones(4, np.float32), "none", clip_model=f"{TINY_CLIP.upper()}:FILE:tiny_clip.pt")
    path = tmp_path / "upper.ply"
    save_ply(attach_field(tiny_scene(4), field, path), path)
    assert main(["query", str(path), "--text", "chair", "--clip-checkpoint", str(tiny_clip), "--scores", str(tmp_path / "s.npy")]) == 0, \
        capsys.readouterr().err
    assert np.load(tmp_path / "s.npy").shape == (4,)


def test_an_hf_hub_model_is_refused_as_such_without_asking_for_a_tag(tmp_path, capsys):
    """Round 83a F3: a field of 'hf-hub:ORG/NAME' was told to pass --pretrained TAG, and with one was refused as an unknown
    model needing --clip-config: drsplat does not load hf-hub: names, which is now what both say."""
    from drsplat.cli import main
    from drsplat.lang import attach_field, build_field
    from drsplat.scene import save_ply
    from tests.test_index import tiny_scene

    with pytest.raises(DrsplatError, match=r"'hf-hub:org/name' is an open_clip hf-hub: name, which drsplat does not load"):
        ClipEncoder("hf-hub:org/name", device="cpu", random_weights=True)
    field = build_field(np.eye(4, 32, dtype=np.float32), np.ones(4, np.float32), "none", clip_model="hf-hub:org/name")
    path = tmp_path / "hub.ply"
    save_ply(attach_field(tiny_scene(4), field, path), path)
    for extra in ([], ["--pretrained", "laion2b_s34b_b88k"]):
        assert main(["query", str(path), "--text", "chair", *extra]) == 1
        err = capsys.readouterr().err
        assert "CLIP model id 'hf-hub:org/name' is an open_clip hf-hub: name" in err and "--pretrained" not in err, err
    for model_id, kind in (("local-dir:/models/x", "local-dir"), ("HF-HUB:org/name", "hf-hub")):  # round 84a F2
        field = build_field(np.eye(4, 32, dtype=np.float32), np.ones(4, np.float32), "none", clip_model=model_id)
        save_ply(attach_field(tiny_scene(4), field, path), path)
        for extra in ([], ["--clip-model", "ViT-B-16"]):  # round 84b F2: with --clip-model it asked for --pretrained
            assert main(["query", str(path), "--text", "chair", *extra]) == 1
            err = capsys.readouterr().err
            assert f"CLIP model id '{model_id}' is an open_clip {kind}: name" in err and "--clip-config" not in err, err
            assert "--pretrained" not in err, err
    check_compatible("hf-hub:org/name", "hf-hub:org/name")
    with pytest.raises(DrsplatError, match="CLIP model mismatch"):
        check_compatible("hf-hub:org/name", "hf-hub")  # an hf-hub id names its weights: not "one names no weights tag"


def test_a_config_open_clip_cannot_build_is_named_not_the_checkpoint(tmp_path, tiny_clip):
    """Round 61c: a --clip-config with a key open_clip's model does not take failed while the checkpoint loaded, and the
    error said the checkpoint was "not a readable torch.save checkpoint". Now it names the config."""
    import open_clip

    bad = tmp_path / "TinyPP-drsplat-test.json"
    bad.write_text(json.dumps({**TINY_CFG, "vision_cfg": {**TINY_CFG["vision_cfg"], "no_such_option": 3}}))
    open_clip.add_model_config(bad)
    with pytest.raises(DrsplatError, match=r"open_clip cannot build model TinyPP-drsplat-test from its config \(--clip-config\)") as err:
        ClipEncoder("TinyPP-drsplat-test", checkpoint=tiny_clip, device="cpu")
    assert "torch.save" not in str(err.value)


def test_an_unknown_model_says_a_config_names_the_model_after_its_file(tmp_path):
    """Round 61c: `--clip-model Foo --clip-config TinyCLIP.json` said Foo "needs its model config: --clip-config" though
    one was given: open_clip names a config's model after its file, which the message now says."""
    from drsplat.features.clip import use_clip_config

    cfg = tmp_path / "SomeName-drsplat-test.json"
    cfg.write_text(json.dumps(TINY_CFG))
    use_clip_config(cfg)
    with pytest.raises(DrsplatError, match=r"open_clip names that model after the file: Foo-drsplat-test.json registers --clip-model Foo-drsplat-test"):
        ClipEncoder("Foo-drsplat-test", device="cpu", random_weights=True)


def test_a_config_given_without_its_model_name_builds_the_model_it_registers(tmp_path, tiny_clip, caplog):
    """Round 66b F1: `features --clip-checkpoint tiny.pt --clip-config TinyCLIP.json` (no --clip-model) built ViT-B-16,
    leaving the config unused, and called the checkpoint "not a readable torch.save checkpoint". The one model a config
    registers is built when --clip-model is not given; a --clip-model the config does not register is said, once."""
    from drsplat.cameras import load_cameras, write_transforms_json
    from drsplat.cli import main
    from drsplat.features.clip import model_for_config
    from drsplat.synthetic import write_dataset

    cfg = tiny_clip.parent / f"{TINY_CLIP}.json"
    assert model_for_config(None, None) == "ViT-B-16" and model_for_config(None, cfg) == TINY_CLIP
    assert model_for_config(None, cfg, default=TINY_CLIP) == TINY_CLIP and model_for_config(TINY_CLIP, cfg) == TINY_CLIP
    folder = tmp_path / "configs"
    folder.mkdir()
    for name in ("A-drsplat-test", "B-drsplat-test"):
        (folder / f"{name}.json").write_text(json.dumps(TINY_CFG))
    (folder / "open_clip_config.json").write_text('{"model_cfg": {}}')  # not a model config: not a model it registers
    with caplog.at_level("WARNING", logger="drsplat.features.clip"):
        assert model_for_config(None, folder) == "ViT-B-16"  # two models: which one is --clip-model's to say
        assert "registers A-drsplat-test, B-drsplat-test, not model ViT-B-16 (--clip-model, by default)" in caplog.text
        caplog.clear()
        assert model_for_config("ViT-B-32", cfg) == "ViT-B-32" and f"registers {TINY_CLIP}, not model ViT-B-32 (--clip-model)" in caplog.text
        caplog.clear()
        model_for_config("B-drsplat-test", folder)
        assert caplog.text == ""
    data = write_dataset(tmp_path / "tiny", "tiny", seed=0, show_progress=False)
    two = tmp_path / "two"
    two.mkdir()
    write_transforms_json(load_cameras(data)[:2], two / "transforms.json")
    assert main(["-q", "features", "--source", str(two), "--out", str(tmp_path / "f"), "--masks", "slic", "--device", "cpu",
                 "--clip-checkpoint", str(tiny_clip), "--clip-config", str(cfg)]) == 0
    manifest = json.loads(next((tmp_path / "f").glob("*.json")).read_text())
    assert manifest["clip_model_id"] == f"{TINY_CLIP}/file:tiny_clip.pt"


def test_check_compatible():
    check_compatible("ViT-B-16/laion2b_s34b_b88k", "vit-b-16/LAION2B_S34B_B88K")
    check_compatible("unknown", "ViT-B-16/laion2b_s34b_b88k")
    check_compatible(None, "ViT-L-14/openai")
    with pytest.raises(DrsplatError, match="CLIP model mismatch: the features were made with ViT-B-16/laion2b_s34b_b88k but the text encoder is ViT-L-14/openai"):
        check_compatible("ViT-B-16/laion2b_s34b_b88k", "ViT-L-14/openai")


def test_bad_checkpoints_are_clear_errors(tmp_path, tiny_clip):
    with pytest.raises(InputError, match="CLIP checkpoint file does not exist"):
        ClipEncoder(TINY_CLIP, checkpoint=tmp_path / "missing.pt", device="cpu")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="not an open_clip checkpoint"):
        ClipEncoder(TINY_CLIP, checkpoint=junk, device="cpu")
    with pytest.raises(InputError, match="not an open_clip checkpoint for ViT-B-32"):
        ClipEncoder("ViT-B-32", checkpoint=tiny_clip, device="cpu")


class _Opaque:  # a pickled object that torch.load(weights_only=True) refuses
    pass


def _bad_checkpoint(tmp_path: Path, kind: str) -> Path:
    import pickle
    import zipfile

    import torch

    path = tmp_path / f"{kind}.pt"
    if kind == "random_bytes":
        path.write_bytes(np.random.default_rng(0).bytes(3000).replace(b"PK", b"pk").lstrip(b"\x80"))
    elif kind == "zip_not_torch":
        with zipfile.ZipFile(path, "w") as z:
            z.writestr("a/data.pkl", b"garbage")
    elif kind == "plain_pickle":
        path.write_bytes(pickle.dumps({"a": 1}, protocol=2))
    elif kind == "python_objects":
        torch.save({"model": _Opaque()}, path)
    elif kind == "wrong_tensors":
        torch.save({"state_dict": {"x": torch.zeros(2)}}, path)
    elif kind == "a_list":
        torch.save([1, 2, 3], path)
    elif kind == "no_tensors":
        torch.save({"epoch": 3}, path)
    return path


@pytest.mark.parametrize("kind, words", [
    ("random_bytes", "neither a torch.save checkpoint (a zip archive) nor a pickle"),
    ("zip_not_torch", "a zip archive, but not a readable torch.save checkpoint"),
    ("plain_pickle", "a pickle, but not of a checkpoint torch can read"),
    ("python_objects", "holds Python objects besides tensors"),
    ("wrong_tensors", "do not fit this architecture"),
    ("a_list", "torch reads it, but it holds list, not a state dict of weights"),  # round 96b F2: "not a readable torch.save checkpoint"
    ("no_tensors", "torch reads it, but it holds a dict of no tensors, not a state dict of weights"),  # round 97a F7
])
def test_a_bad_clip_checkpoint_is_one_short_error_saying_what_the_file_is(tmp_path, tiny_clip, kind, words):
    """torch's messages ran into the error line: a paragraph on weights_only for any legacy-format
    failure, 'Expected hasRecord("version")' for a zip. Now a few words on what the file is.
    (tiny_clip registers the architecture with open_clip: run alone, the test failed without it.)"""
    path = _bad_checkpoint(tmp_path, kind)
    with pytest.raises(InputError) as exc:
        ClipEncoder(TINY_CLIP, checkpoint=path, device="cpu")
    msg = str(exc.value)
    assert f"{path}" in msg and f"not an open_clip checkpoint for {TINY_CLIP}: " in msg and words in msg, msg
    assert "\n" not in msg and len(msg) < 200 + len(str(path)) and "weights_only` argument" not in msg, msg


def _offline_env(monkeypatch, tmp_path):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.delenv("HF_HUB_CACHE", raising=False)


def test_unreachable_hub_fails_fast_with_the_same_sentence(monkeypatch, tmp_path):
    import open_clip.pretrained

    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.setattr("drsplat.features.weights.host_reachable", lambda url: False)
    monkeypatch.setattr(open_clip.pretrained, "download_pretrained", lambda *a, **k: pytest.fail("no download without network"))
    with pytest.raises(WeightsUnavailableError) as err:
        resolve_pretrained_weights("ViT-B-16", "laion2b_s34b_b88k")
    assert str(err.value) == OFFLINE_CLIP_MESSAGE


def test_offline_without_cache_is_one_sentence(monkeypatch, tmp_path):
    _offline_env(monkeypatch, tmp_path)
    with pytest.raises(WeightsUnavailableError) as err:
        ClipEncoder(device="cpu")
    assert str(err.value) == OFFLINE_CLIP_MESSAGE


def test_failed_download_is_the_same_sentence(monkeypatch, tmp_path):
    import open_clip.pretrained

    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))

    def no_network(*args, **kwargs):
        raise ConnectionError("Failed to resolve 'huggingface.co'")  # what httpx/requests raise, in spirit

    monkeypatch.setattr(open_clip.pretrained, "download_pretrained", no_network)
    monkeypatch.setattr("drsplat.features.weights.host_reachable", lambda url: True)  # the probe passes, the download fails
    with pytest.raises(WeightsUnavailableError) as err:
        resolve_pretrained_weights("ViT-B-16", "laion2b_s34b_b88k")
    assert str(err.value) == OFFLINE_CLIP_MESSAGE
    assert err.value.__suppress_context__


def test_weights_in_the_hub_cache_are_used_offline(monkeypatch, tmp_path):
    _offline_env(monkeypatch, tmp_path)
    snapshot = tmp_path / "hf" / "hub" / "models--laion--CLIP-ViT-B-16-laion2B-s34B-b88K" / "snapshots" / "abc123"
    snapshot.mkdir(parents=True)
    (snapshot / "open_clip_model.safetensors").write_bytes(b"weights")
    refs = snapshot.parent.parent / "refs"
    refs.mkdir()
    (refs / "main").write_text("abc123")
    path = resolve_pretrained_weights("ViT-B-16", "laion2b_s34b_b88k")
    assert Path(path) == snapshot / "open_clip_model.safetensors"


def test_unknown_tag_names_the_known_ones():
    with pytest.raises(DrsplatError, match="unknown OpenCLIP pretrained tag 'nope' for model 'ViT-B-16' .*laion2b_s34b_b88k"):
        resolve_pretrained_weights("ViT-B-16", "nope")


def test_an_unknown_model_or_tag_with_a_newline_is_shown_escaped():
    """Round 54: `--clip-model $'a\\nb'` printed a raw newline inside the error (a forged second line)."""
    from drsplat.features.clip import ClipEncoder

    with pytest.raises(DrsplatError) as err:
        ClipEncoder(model="a\nb", device="cpu")
    assert "\n" not in str(err.value) and "'a\\nb'" in str(err.value), err.value
    with pytest.raises(DrsplatError) as err:
        resolve_pretrained_weights("ViT-B-16", "x\ny")
    assert "\n" not in str(err.value) and "'x\\ny'" in str(err.value), err.value


def test_file_label_asks_for_the_checkpoint():
    with pytest.raises(WeightsUnavailableError, match=r"made with a local checkpoint \(tiny_clip.pt\) of ViT-B-16; pass --clip-checkpoint PATH"):
        ClipEncoder("ViT-B-16", pretrained="file:tiny_clip.pt", device="cpu")


def test_text_queries_read_the_model_config_features_read(tmp_path):
    """Features made with `features --clip-config` (an architecture open_clip does not ship) could
    not be queried by text: `query`, `segment` and the viewer had no --clip-config, and the error
    did not name it (a probe on real photos, 2026-11-30). In a fresh process, as a user runs it."""
    import subprocess
    import sys

    import open_clip

    from drsplat.lang import attach_field, build_field
    from drsplat.scene import save_ply
    from tests.test_index import tiny_scene

    name = "TinyCLIP-cfgtest"
    cfg = tmp_path / f"{name}.json"
    cfg.write_text(json.dumps(TINY_CFG))
    open_clip.add_model_config(cfg)  # this process only: the commands below run in new ones
    torch.manual_seed(0)
    ckpt = tmp_path / "w.pt"
    torch.save(open_clip.create_model(name).state_dict(), ckpt)
    feats = np.eye(4, 32, dtype=np.float32)
    field = build_field(feats, np.ones(4, np.float32), "none", clip_model=f"{name}/file:w.pt")
    reg = tmp_path / "reg.ply"
    save_ply(attach_field(tiny_scene(4), field, reg), reg)
    root = Path(__file__).resolve().parents[1]

    def drsplat(*argv: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "drsplat", *argv], capture_output=True, text=True, cwd=root, timeout=300)

    refused = drsplat("query", str(reg), "--text", "a chair", "--clip-checkpoint", str(ckpt))
    assert refused.returncode == 1 and "--clip-config CONFIG.json" in refused.stderr, refused.stderr
    scored = drsplat("query", str(reg), "--text", "a chair", "--clip-checkpoint", str(ckpt), "--clip-config", str(cfg), "--scores",
                     str(tmp_path / "s.npy"))
    assert scored.returncode == 0, scored.stderr
    assert np.load(tmp_path / "s.npy").shape == (4,)
    labelled = drsplat("segment", str(reg), "--labels", "chair,table", "--clip-checkpoint", str(ckpt), "--clip-config", str(cfg), "--out",
                       str(tmp_path / "l.npy"))
    assert labelled.returncode == 0, labelled.stderr


def test_a_tokenizer_that_needs_a_missing_package_or_the_hub_is_one_sentence(tiny_clip, monkeypatch):
    """Round 40: `--clip-model ViT-B-16-SigLIP` loaded its weights, then stopped with a traceback from
    open_clip.get_tokenizer ("No module named 'transformers'"); offline, its Hugging Face tokenizer likewise."""
    import open_clip

    from drsplat.errors import DrsplatError, WeightsUnavailableError

    def missing(model):
        raise ModuleNotFoundError("No module named 'transformers'", name="transformers")

    monkeypatch.setattr(open_clip, "get_tokenizer", missing)
    with pytest.raises(DrsplatError, match=r"needs the Python package 'transformers', which is not installed \(pip install transformers\)"):
        ClipEncoder(TINY_CLIP, checkpoint=tiny_clip, device="cpu")

    def offline(model):
        raise OSError("We couldn't connect to 'https://huggingface.co'")

    monkeypatch.setattr(open_clip, "get_tokenizer", offline)
    with pytest.raises(WeightsUnavailableError, match="is not in the local Hugging Face cache and cannot be downloaded"):
        ClipEncoder(TINY_CLIP, checkpoint=tiny_clip, device="cpu")


def test_text_queries_refuse_a_clip_checkpoint_other_than_the_features_weights(tiny_clip, tmp_path, monkeypatch):
    """Round 57c: `query --text ... --clip-checkpoint OTHER.pt` scored with any weights file: --pretrained defaults to the
    PLY's own tag, so the encoder took the field's model id and the id check always passed (scores from another
    embedding space, exit 0). The registered PLY now carries the features' weights digest (`clip_weights`, from the
    feature folder's manifest) through registration and exports, and a text encoder of another file is refused;
    the same file under another name, or a PLY without the digest, is not."""
    import shutil

    from drsplat.commands.common import load_registered
    from drsplat.errors import DrsplatError, InputError
    from drsplat.features.modelid import weights_digest
    from drsplat.lang import attach_field, build_field
    from drsplat.query import text_embeddings
    from drsplat.scene import save_ply
    from tests.test_index import tiny_scene

    digest = weights_digest(tiny_clip)
    field = build_field(np.eye(4, 32, dtype=np.float32), np.ones(4, np.float32), "none", clip_model=f"{TINY_CLIP}/file:tiny_clip.pt",
                        clip_weights=digest)
    reg = tmp_path / "reg.ply"
    save_ply(attach_field(tiny_scene(4), field, reg), reg)
    _, read = load_registered(reg)
    assert read.clip_weights == digest and read.subset(np.array([0, 2])).clip_weights == digest
    other = make_tiny_clip(tmp_path / "other", seed=1)
    with pytest.raises(DrsplatError, match=rf"CLIP weights mismatch: the registered features were made with a weights file of size:sha1 {digest}"):
        text_embeddings(ClipEncoder(TINY_CLIP, pretrained="file:tiny_clip.pt", checkpoint=other, device="cpu"), ["a chair"], read)
    renamed = tmp_path / "renamed.pt"
    shutil.copyfile(tiny_clip, renamed)
    assert text_embeddings(ClipEncoder(TINY_CLIP, pretrained="file:tiny_clip.pt", checkpoint=renamed, device="cpu"), ["a chair"], read).shape == (1, 32)
    unrecorded = build_field(np.eye(4, 32, dtype=np.float32), np.ones(4, np.float32), "none", clip_model=f"{TINY_CLIP}/file:tiny_clip.pt")
    assert text_embeddings(ClipEncoder(TINY_CLIP, pretrained="file:tiny_clip.pt", checkpoint=other, device="cpu"), ["a"], unrecorded).shape == (1, 32)
    # an altered entry is refused when read
    text = reg.read_bytes().replace(f"clip_weights={digest}".encode(), f"clip_weights={'x' * len(digest)}".encode())
    (tmp_path / "bad.ply").write_bytes(text)
    with pytest.raises(InputError, match=r"the metadata entry clip_weights=x+.* is not a weights file's size:sha1, as registration"):
        load_registered(tmp_path / "bad.ply")


def test_registration_carries_the_feature_folders_clip_weights_into_the_ply(tmp_path, capsys):
    """The registered PLY records the `clip_weights` its feature folder's manifest gives (what `drsplat features` writes),
    so that queries can check their encoder's file; a folder without one registers as before."""
    import json

    from drsplat.cli import main
    from drsplat.commands.common import load_registered

    assert main(["synth", str(tmp_path / "d"), "--preset", "tiny", "--no-progress", "-q"]) == 0
    manifest = tmp_path / "d" / "features" / "manifest.json"
    doc = json.loads(manifest.read_text())
    digest = "1234:" + "ab" * 20
    manifest.write_text(json.dumps({**doc, "clip_weights": digest}))
    argv = ["register", str(tmp_path / "d" / "scene.ply"), "--source", str(tmp_path / "d"), "--features", str(tmp_path / "d" / "features"),
            "--aggregate", "paper", "--no-progress", "-q"]
    assert main([*argv, "--out", str(tmp_path / "r.ply")]) == 0
    assert load_registered(tmp_path / "r.ply")[1].clip_weights == digest
    assert main(["info", str(tmp_path / "r.ply")]) == 0
    assert "(weights 1234 bytes, sha1 abababababab)" in capsys.readouterr().out
    manifest.write_text(json.dumps(doc))
    assert main([*argv, "--out", str(tmp_path / "plain.ply")]) == 0
    assert load_registered(tmp_path / "plain.ply")[1].clip_weights is None
    # round 58b: a file of fewer Gaussians than its metadata's bytes, metadata past 255 bytes (clip_weights made ordinary names
    # reach it): the widened lang_meta columns were declared ushort and cut the uint cells, so without comments nothing decoded
    import dataclasses

    from drsplat.lang.plyformat import read_field
    from drsplat.scene import load_ply, save_ply

    manifest.write_text(json.dumps({**doc, "clip_weights": digest}))
    scene = load_ply(tmp_path / "d" / "scene.ply")
    save_ply(scene.subset(np.arange(150)), tmp_path / "d" / "sub.ply")
    out = tmp_path / ("x" * 150 + ".ply")
    argv[1] = str(tmp_path / "d" / "sub.ply")
    rows = np.random.default_rng(0).normal(size=(300, 512)).astype(np.float32)
    np.save(tmp_path / "e.npy", rows / np.linalg.norm(rows, axis=1, keepdims=True))
    assert main(["pq", "train", "--embeddings", str(tmp_path / "e.npy"), "--out", str(tmp_path / "cb.faiss"), "--m", "8"]) == 0
    assert main([*argv, "--codebook", str(tmp_path / "cb.faiss"), "--out", str(out)]) == 0
    written = load_ply(out)
    field = read_field(dataclasses.replace(written, comments=[c for c in written.comments if not c.startswith("drsplat.lang")]), out)
    assert field.clip_weights == digest and field.kind == "pq"
