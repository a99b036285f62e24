#!/usr/bin/env python3
"""Independent functional JAX reference of the XFactor model (shared/xfactor/SPEC.md).

Plain-dict parameters keyed by their flax names without the ``params.`` prefix, e.g.
``PoseEnc.layers_0.Dense_0.kernel``. Everything runs in float64 (x64 enabled); fixture files
are stored in float32 (pmask int32), with the same layout as the authors' xfactor-tiny fixture.

Usage:
  python xfactor_reference.py validate FIXTURE.safetensors        # compare against a fixture
  python xfactor_reference.py generate NAME OUTDIR [--batch ...]  # write OUTDIR/NAME.{safetensors,json}
  python xfactor_reference.py generate-defaults OUTDIR            # xfactor-deep and xfactor-manyviews
"""

import argparse
import json
import math
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
# Fixtures are made and validated on the CPU (float64 where the release allows it); the `bench`
# peer runs on the host's best platform (a GPU where JAX has one), unless
# XFACTOR_JAX_PLATFORMS names one (`cpu`, `cuda`).
if os.environ.get("XFACTOR_JAX_PLATFORMS"):
    jax.config.update("jax_platforms", os.environ["XFACTOR_JAX_PLATFORMS"])
elif sys.argv[1:2] != ["bench"]:
    jax.config.update("jax_platforms", "cpu")

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from safetensors.numpy import load_file, save_file  # noqa: E402

LAYOUT = (
    "images are B x V x H x W x 3 (channels last), values in [-1,1]; "
    "pmask is B x (H/p*W/p) row-major patch grid, 0/1"
)

# ----------------------------------------------------------------------------------------
# Building blocks
# ----------------------------------------------------------------------------------------


def gelu(x):
    # tanh approximation (jax.nn.gelu default, approximate=True)
    return 0.5 * x * (1.0 + jnp.tanh(math.sqrt(2.0 / math.pi) * (x + 0.044715 * x**3)))


def dense(p, pre, x, bias=True):
    y = x @ p[pre + ".kernel"]
    if bias:
        y = y + p[pre + ".bias"]
    return y


def layer_norm(p, pre, x, bias=True, eps=1e-6):
    # flax LayerNorm: var = max(0, E[x^2] - E[x]^2)
    mean = jnp.mean(x, axis=-1, keepdims=True)
    mean2 = jnp.mean(x * x, axis=-1, keepdims=True)
    var = jnp.maximum(0.0, mean2 - mean * mean)
    y = (x - mean) * jax.lax.rsqrt(var + eps)
    y = y * p[pre + ".scale"]
    if bias:
        y = y + p[pre + ".bias"]
    return y


def rms_norm(p, pre, x, eps=1e-5):
    # x: (..., h, d); alpha: (h, d)
    ms = jnp.mean(x * x, axis=-1, keepdims=True)
    return p[pre + ".alpha"] * x * jax.lax.rsqrt(ms + eps)


def mlp2(p, pre, x):
    return dense(p, pre + ".Dense_1", gelu(dense(p, pre + ".Dense_0", x)))


def mlp3(p, pre, x):
    h = gelu(dense(p, pre + ".Dense_0", x))
    h = gelu(dense(p, pre + ".Dense_1", h))
    return dense(p, pre + ".Dense_2", h)


def patchify(img, ps):
    # img: (..., H, W, 3) -> (..., T, ps*ps*3); token = (row-in-patch, col-in-patch, channel)
    *lead, H, W, c = img.shape
    gh, gw = H // ps, W // ps
    x = img.reshape(*lead, gh, ps, gw, ps, c)
    n = len(lead)
    perm = list(range(n)) + [n, n + 2, n + 1, n + 3, n + 4]
    x = x.transpose(perm)
    return x.reshape(*lead, gh * gw, ps * ps * c)


def unpatchify(tok, ps, H, W):
    *lead, T, D = tok.shape
    c = D // (ps * ps)
    gh, gw = H // ps, W // ps
    x = tok.reshape(*lead, gh, gw, ps, ps, c)
    n = len(lead)
    perm = list(range(n)) + [n, n + 2, n + 1, n + 3, n + 4]
    x = x.transpose(perm)
    return x.reshape(*lead, H, W, c)


def rope_angles(gh, gw, d):
    """(gh*gw, d) angles for the 2D RoPE table, patches in row-major order."""
    assert d % 4 == 0
    i = np.arange(d // 4, dtype=np.float64)
    w = 10000.0 ** (-i / (d / 4))
    w = np.repeat(w, 2)  # (d/2): w0 w0 w1 w1 ...
    I, J = np.meshgrid(np.arange(gh, dtype=np.float64), np.arange(gw, dtype=np.float64), indexing="ij")
    I = I.reshape(-1, 1)
    J = J.reshape(-1, 1)
    return np.concatenate([w[None] * I, w[None] * J], axis=-1)


def rope_table(gh, gw, d, n_identity=0):
    a = rope_angles(gh, gw, d)
    cos, sin = np.cos(a), np.sin(a)
    if n_identity:
        cos = np.concatenate([cos, np.ones((n_identity, d))], 0)
        sin = np.concatenate([sin, np.zeros((n_identity, d))], 0)
    return jnp.asarray(cos), jnp.asarray(sin)


def apply_rope(x, cos, sin):
    # x: (B, V, T, h, d); cos/sin: (T, d)
    x2 = x.reshape(*x.shape[:-1], -1, 2)
    rot = jnp.stack([-x2[..., 1], x2[..., 0]], axis=-1).reshape(x.shape)
    return x * cos[:, None, :] + rot * sin[:, None, :]


def attention(q, k, v, seg_q, seg_k):
    # q,k,v: (B, N, h, d); seg: (B, N)
    d = q.shape[-1]
    logits = jnp.einsum("bqhd,bkhd->bhqk", q, k) / math.sqrt(d)
    allowed = (seg_q[:, :, None] == seg_k[:, None, :])[:, None]
    logits = jnp.where(allowed, logits, -jnp.inf)
    w = jax.nn.softmax(logits, axis=-1)
    return jnp.einsum("bhqk,bkhd->bqhd", w, v)


def mv_layer(p, pre, z, seg, cos, sin, num_heads):
    """Fused global + per-view attention layer. z: (B, V, T', C); seg: (B, V, T')."""
    B, V, T, C = z.shape
    h = num_heads
    d = C // h
    u = layer_norm(p, pre + ".LayerNorm_0", z, bias=False)
    qkv = dense(p, pre + ".Dense_0", u, bias=False)
    q, k, v, qs, ks, vs = [t.reshape(B, V, T, h, d) for t in jnp.split(qkv, 6, axis=-1)]
    q = rms_norm(p, pre + ".RMSNorm_0", q)
    k = rms_norm(p, pre + ".RMSNorm_1", k)
    qs = rms_norm(p, pre + ".RMSNorm_2", qs)
    ks = rms_norm(p, pre + ".RMSNorm_3", ks)
    q, k, qs, ks = [apply_rope(t, cos, sin) for t in (q, k, qs, ks)]
    # global: all views, view-major
    segf = seg.reshape(B, V * T)
    g = attention(q.reshape(B, V * T, h, d), k.reshape(B, V * T, h, d), v.reshape(B, V * T, h, d), segf, segf)
    g = g.reshape(B, V, T, C)
    # per view
    segv = seg.reshape(B * V, T)
    s = attention(qs.reshape(B * V, T, h, d), ks.reshape(B * V, T, h, d), vs.reshape(B * V, T, h, d), segv, segv)
    s = s.reshape(B, V, T, C)
    o = dense(p, pre + ".Dense_1", jnp.concatenate([g, s], axis=-1))
    z0 = z + p[pre + ".LayerScale_0.alpha"] * o
    m = mlp2(p, pre + ".MLP2_0", gelu(layer_norm(p, pre + ".LayerNorm_1", z0)))
    return z0 + p[pre + ".LayerScale_1.alpha"] * m


def num_layers_of(p, mod):
    n = 0
    while f"{mod}.layers_{n}.Dense_0.kernel" in p:
        n += 1
    return n


# ----------------------------------------------------------------------------------------
# PoseEnc and Render
# ----------------------------------------------------------------------------------------


def pose_enc(p, images, mask, cfg):
    """images (B, V, H, W, 3); mask (B, T) 0/1 or None.
    Returns (B, V, 2, Cp) with a mask, (B, V, Cp) without."""
    B, V, H, W, _ = images.shape
    ps, h = cfg["patch_size"], cfg["num_heads"]
    gh, gw = H // ps, W // ps
    T = gh * gw
    x = dense(p, "PoseEnc.Dense_0", patchify(images, ps))  # (B, V, T, C)
    C = x.shape[-1]
    ge = p["PoseEnc.global_embed"]
    G = ge.shape[0]
    ge2 = jnp.broadcast_to(jnp.concatenate([ge, ge], 0), (B, V, 2 * G, C))
    z = jnp.concatenate([x, ge2], axis=2)
    if mask is None:
        pseg = jnp.zeros((B, T), jnp.int32)
    else:
        pseg = jnp.asarray(mask).astype(jnp.int32)
    gseg = jnp.concatenate([jnp.zeros((G,), jnp.int32), jnp.ones((G,), jnp.int32)])
    seg = jnp.concatenate([pseg, jnp.broadcast_to(gseg, (B, 2 * G))], axis=1)
    seg = jnp.broadcast_to(seg[:, None], (B, V, T + 2 * G))
    cos, sin = rope_table(gh, gw, C // h, n_identity=2 * G)
    for i in range(num_layers_of(p, "PoseEnc")):
        z = mv_layer(p, f"PoseEnc.layers_{i}", z, seg, cos, sin, h)
    zt = jnp.stack([z[:, :, T], z[:, :, T + G]], axis=2)  # (B, V, 2, C)
    zt = gelu(layer_norm(p, "PoseEnc.LayerNorm_0", zt))
    z0 = jnp.broadcast_to(zt[:, :1], zt.shape)
    head = "PoseEnc.PoseHead_0.MLP3_0"
    P = mlp3(p, head, jnp.concatenate([zt, z0], -1)) - mlp3(p, head, jnp.concatenate([z0, z0], -1))
    if mask is None:
        return P[:, :, 0]
    return P


def render(p, ctx, poses, mask, cfg):
    """ctx (B, V-1, H, W, 3); poses (B, V, 2, Cp) or (B, V, Cp); mask (B, T) or None.
    Returns (B, H, W, 3)."""
    B, Vc, H, W, _ = ctx.shape
    ps, h = cfg["patch_size"], cfg["num_heads"]
    gh, gw = H // ps, W // ps
    T = gh * gw
    if poses.ndim == 3:
        poses = jnp.stack([poses, poses], axis=2)
    if mask is None:
        m = jnp.zeros((B, T), poses.dtype)
        seg = jnp.zeros((B, T), jnp.int32)
    else:
        m = jnp.asarray(mask).astype(poses.dtype)
        seg = jnp.asarray(mask).astype(jnp.int32)
    m = m[:, None, :, None]  # (B, 1, T, 1)
    tokpose = (1.0 - m) * poses[:, :, 0:1, :] + m * poses[:, :, 1:2, :]  # (B, V, T, Cp)
    cp = patchify(ctx, ps)
    zc = mlp2(p, "Render.MLP2_0", jnp.concatenate([cp, tokpose[:, :Vc]], -1))
    zt = mlp2(p, "Render.MLP2_1", tokpose[:, Vc:])
    z = jnp.concatenate([zc, zt], axis=1)  # (B, V, T, C)
    C = z.shape[-1]
    V = Vc + 1
    segv = jnp.broadcast_to(seg[:, None], (B, V, T))
    cos, sin = rope_table(gh, gw, C // h)
    for i in range(num_layers_of(p, "Render")):
        z = mv_layer(p, f"Render.layers_{i}", z, segv, cos, sin, h)
    y = gelu(layer_norm(p, "Render.LayerNorm_0", z[:, -1]))
    y = mlp3(p, "Render.MLP3_0", y)
    y = 2.0 * (jax.nn.sigmoid(y) - 0.5)
    return unpatchify(y, ps, H, W)


def swap_slots(P):
    return P[:, :, ::-1]


def forward_all(p, inp, cfg):
    pair, pmask = inp["pair"], inp["pmask"]
    pm = pose_enc(p, pair, pmask, cfg)
    pf = pose_enc(p, pair, None, cfg)
    rm = render(p, pair[:, :1], swap_slots(pm), pmask, cfg)
    rf = render(p, pair[:, :1], pf, None, cfg)
    rmv = render(p, inp["ctx_mv"], inp["pose_mv"], None, cfg)
    l1 = jnp.mean(jnp.abs(pair[:, 1] - rm))
    return {
        "pose_masked": pm,
        "pose_full": pf,
        "render_masked": rm,
        "render_full": rf,
        "render_mv": rmv,
        "l1_loss": l1.reshape(1),
    }


def l1_loss(p, inp, cfg):
    pair, pmask = inp["pair"], inp["pmask"]
    pm = pose_enc(p, pair, pmask, cfg)
    rm = render(p, pair[:, :1], swap_slots(pm), pmask, cfg)
    return jnp.mean(jnp.abs(pair[:, 1] - rm))


def compute(p, inp, cfg):
    p64 = {k: jnp.asarray(v, jnp.float64) for k, v in p.items()}
    inp64 = {
        "pair": jnp.asarray(inp["pair"], jnp.float64),
        "pmask": jnp.asarray(inp["pmask"], jnp.int32),
        "ctx_mv": jnp.asarray(inp["ctx_mv"], jnp.float64),
        "pose_mv": jnp.asarray(inp["pose_mv"], jnp.float64),
    }
    outs = jax.jit(lambda pp, ii: forward_all(pp, ii, cfg))(p64, inp64)
    grads = jax.jit(jax.grad(lambda pp, ii: l1_loss(pp, ii, cfg)))(p64, inp64)
    return {k: np.asarray(v) for k, v in outs.items()}, {k: np.asarray(v) for k, v in grads.items()}


# ----------------------------------------------------------------------------------------
# Fixture I/O
# ----------------------------------------------------------------------------------------


def load_fixture(path):
    d = load_file(path)
    params = {k[len("params."):]: v for k, v in d.items() if k.startswith("params.")}
    inp = {k[len("input."):]: v for k, v in d.items() if k.startswith("input.")}
    out = {k[len("output."):]: v for k, v in d.items() if k.startswith("output.")}
    grads = {k[len("grads."):]: v for k, v in d.items() if k.startswith("grads.")}
    cfg_path = os.path.splitext(path)[0] + ".json"
    with open(cfg_path) as f:
        cfg = json.load(f)
    return cfg, params, inp, out, grads


def compare(path, verbose=True):
    cfg, params, inp, out_ref, grads_ref = load_fixture(path)
    outs, grads = compute(params, inp, cfg)
    out_err = {}
    for k in sorted(out_ref):
        out_err[k] = float(np.max(np.abs(outs[k] - out_ref[k].astype(np.float64))))
    assert set(grads) == set(grads_ref), set(grads) ^ set(grads_ref)
    grad_err = {}
    for k in sorted(grads_ref):
        g_ref = grads_ref[k].astype(np.float64)
        den = np.max(np.abs(g_ref))
        num = np.max(np.abs(grads[k] - g_ref))
        grad_err[k] = float(num / den) if den > 0 else float(num)
    if verbose:
        print(f"fixture: {path}")
        for k, e in out_err.items():
            print(f"  output.{k:15s} max abs err = {e:.3e}")
        worst = sorted(grad_err.items(), key=lambda kv: -kv[1])
        print(f"  grads: worst relative error = {worst[0][1]:.3e} ({worst[0][0]})")
        for k, e in worst[:5]:
            print(f"    {k:55s} {e:.3e}")
        print(f"  l1_loss ours {float(outs['l1_loss'][0]):.9f} vs json {cfg.get('l1_loss')}")
    return out_err, grad_err


# ----------------------------------------------------------------------------------------
# Generator
# ----------------------------------------------------------------------------------------


def param_shapes(cfg):
    C = cfg["features"]
    h = cfg["num_heads"]
    d = C // h
    ps = cfg["patch_size"]
    P = 3 * ps * ps
    Cp = cfg["pose_dim"]
    G = cfg["global_tokens"]
    L = cfg["num_layers"]
    s = {}

    def layer(pre):
        s[pre + ".LayerNorm_0.scale"] = (C,)
        s[pre + ".Dense_0.kernel"] = (C, 6 * C)
        for i in range(4):
            s[pre + f".RMSNorm_{i}.alpha"] = (h, d)
        s[pre + ".Dense_1.kernel"] = (2 * C, C)
        s[pre + ".Dense_1.bias"] = (C,)
        s[pre + ".LayerScale_0.alpha"] = (C,)
        s[pre + ".LayerNorm_1.scale"] = (C,)
        s[pre + ".LayerNorm_1.bias"] = (C,)
        s[pre + ".MLP2_0.Dense_0.kernel"] = (C, 4 * C)
        s[pre + ".MLP2_0.Dense_0.bias"] = (4 * C,)
        s[pre + ".MLP2_0.Dense_1.kernel"] = (4 * C, C)
        s[pre + ".MLP2_0.Dense_1.bias"] = (C,)
        s[pre + ".LayerScale_1.alpha"] = (C,)

    def dense_(pre, i, o):
        s[pre + ".kernel"] = (i, o)
        s[pre + ".bias"] = (o,)

    dense_("PoseEnc.Dense_0", P, C)
    s["PoseEnc.global_embed"] = (G, C)
    for i in range(L):
        layer(f"PoseEnc.layers_{i}")
    s["PoseEnc.LayerNorm_0.scale"] = (C,)
    s["PoseEnc.LayerNorm_0.bias"] = (C,)
    dense_("PoseEnc.PoseHead_0.MLP3_0.Dense_0", 2 * C, 4 * C)
    dense_("PoseEnc.PoseHead_0.MLP3_0.Dense_1", 4 * C, C)
    dense_("PoseEnc.PoseHead_0.MLP3_0.Dense_2", C, Cp)
    dense_("Render.MLP2_0.Dense_0", P + Cp, 4 * C)
    dense_("Render.MLP2_0.Dense_1", 4 * C, C)
    dense_("Render.MLP2_1.Dense_0", Cp, 4 * C)
    dense_("Render.MLP2_1.Dense_1", 4 * C, C)
    for i in range(L):
        layer(f"Render.layers_{i}")
    s["Render.LayerNorm_0.scale"] = (C,)
    s["Render.LayerNorm_0.bias"] = (C,)
    dense_("Render.MLP3_0.Dense_0", C, 4 * C)
    dense_("Render.MLP3_0.Dense_1", 4 * C, C)
    dense_("Render.MLP3_0.Dense_2", C, P)
    return s


def init_params(cfg, rng, perturb=True):
    """SPEC initialisation, then (perturb=True) random LayerScale / norm scales / biases so
    every path contributes visibly."""
    p = {}
    for name, shape in sorted(param_shapes(cfg).items()):
        leaf = name.rsplit(".", 1)[1]
        kind = name.rsplit(".", 2)[1]
        if leaf == "kernel":
            fi, fo = shape
            lim = math.sqrt(6.0 / (fi + fo))
            v = rng.uniform(-lim, lim, shape)
        elif leaf == "bias" and kind.startswith("Dense"):
            v = rng.normal(0.0, 1e-6, shape)
            if perturb:
                v = 0.05 * rng.normal(size=shape)
        elif leaf == "bias":  # LayerNorm bias
            v = np.zeros(shape)
            if perturb:
                v = 0.05 * rng.normal(size=shape)
        elif leaf == "scale" or kind.startswith("RMSNorm"):
            v = np.ones(shape)
            if perturb:
                v = 1.0 + 0.1 * rng.normal(size=shape)
        elif kind.startswith("LayerScale"):
            v = np.full(shape, 0.01)
            if perturb:
                v = rng.uniform(0.5, 1.5, shape) * rng.choice([-1.0, 1.0], shape)
        elif name == "PoseEnc.global_embed":
            v = rng.normal(0.0, 0.02, shape)
            if perturb:
                v = rng.normal(0.0, 0.5, shape)
        else:
            raise ValueError(name)
        p[name] = v.astype(np.float64)
    return p


def quadrant_mask(gh, gw, rng):
    quads = rng.choice(4, size=2, replace=False)
    m = np.zeros((gh, gw), np.int32)
    rh, rw = gh // 2, gw // 2
    for q in quads:
        r0 = 0 if q < 2 else rh
        r1 = rh if q < 2 else gh
        c0 = 0 if q % 2 == 0 else rw
        c1 = rw if q % 2 == 0 else gw
        m[r0:r1, c0:c1] = 1
    return m.reshape(-1)


def generate(name, outdir, cfg):
    rng = np.random.default_rng(cfg["seed"])
    B, H, W, ps = cfg["batch"], cfg["height"], cfg["width"], cfg["patch_size"]
    assert H % ps == 0 and W % ps == 0
    assert (cfg["features"] // cfg["num_heads"]) % 4 == 0
    gh, gw = H // ps, W // ps
    Vc, Cp = cfg["context_views_mv"], cfg["pose_dim"]
    params = init_params(cfg, rng)
    # round to float32 first so the stored file is exactly what we computed from
    params = {k: v.astype(np.float32) for k, v in params.items()}
    pose_mv = rng.normal(size=(B, Vc + 1, Cp))
    pose_mv[:, 0] = 0.0  # reference pose is zero by construction
    inp = {
        "pair": rng.uniform(-1.0, 1.0, (B, 2, H, W, 3)).astype(np.float32),
        "pmask": np.stack([quadrant_mask(gh, gw, rng) for _ in range(B)]).astype(np.int32),
        "ctx_mv": rng.uniform(-1.0, 1.0, (B, Vc, H, W, 3)).astype(np.float32),
        "pose_mv": pose_mv.astype(np.float32),
    }
    outs, grads = compute(params, inp, cfg)
    tensors = {}
    for k, v in params.items():
        tensors["params." + k] = np.ascontiguousarray(v, np.float32)
    for k, v in inp.items():
        tensors["input." + k] = np.ascontiguousarray(v)
    for k, v in outs.items():
        tensors["output." + k] = np.ascontiguousarray(v, np.float32)
    for k, v in grads.items():
        tensors["grads." + k] = np.ascontiguousarray(v, np.float32)
    os.makedirs(outdir, exist_ok=True)
    st = os.path.join(outdir, name + ".safetensors")
    save_file(tensors, st)
    meta = dict(cfg)
    meta["layout"] = LAYOUT
    meta["l1_loss"] = float(np.float32(outs["l1_loss"][0]))
    keys = ["batch", "height", "width", "patch_size", "features", "num_heads", "num_layers",
            "pose_dim", "global_tokens", "context_views_mv", "seed", "layout", "l1_loss"]
    with open(os.path.join(outdir, name + ".json"), "w") as f:
        json.dump({k: meta[k] for k in keys}, f, indent=2)
        f.write("\n")
    print(f"wrote {st} ({os.path.getsize(st)} bytes), l1_loss={meta['l1_loss']:.6f}")
    print("  output magnitudes:", {k: float(np.max(np.abs(v))) for k, v in outs.items()})
    return st


def bench(cfg, steps):
    """Times one jitted float32 stage-1 step (PoseEnc with the quadrant mask, Render from the
    swapped poses, the L1 loss, and its gradient) as the Rust benchmark `model_step` does, and
    prints `jax_compile_s=... jax_step_s=... jax_min_step_s=...` (the median and the fastest of
    `steps` steps after the compiling one)."""

    jax.config.update("jax_enable_x64", False)
    rng = np.random.default_rng(cfg["seed"])
    B, H, W, ps = cfg["batch"], cfg["height"], cfg["width"], cfg["patch_size"]
    gh, gw = H // ps, W // ps
    params = {k: jnp.asarray(v, jnp.float32) for k, v in init_params(cfg, rng, perturb=False).items()}
    inp = {
        "pair": jnp.asarray(rng.uniform(-1.0, 1.0, (B, 2, H, W, 3)), jnp.float32),
        "pmask": jnp.asarray(np.stack([quadrant_mask(gh, gw, rng) for _ in range(B)]), jnp.int32),
    }
    step = jax.jit(jax.value_and_grad(lambda pp, ii: l1_loss(pp, ii, cfg)))
    start = time.perf_counter()
    loss, grads = step(params, inp)
    jax.block_until_ready(grads)
    compile_s = time.perf_counter() - start
    assert np.isfinite(float(loss))
    times = []
    for _ in range(steps):
        start = time.perf_counter()
        jax.block_until_ready(step(params, inp))
        times.append(time.perf_counter() - start)
    times.sort()
    device = jax.devices()[0]
    stats = device.memory_stats() or {}
    memory = " ".join(f"jax_{key}={stats[key]}" for key in ("peak_bytes_in_use", "bytes_limit")
                      if key in stats)
    print(f"jax_version={jax.__version__} jax_platform={device.platform} "
          f"jax_device=\"{device.device_kind}\" "
          f"jax_matmul_precision={jax.config.jax_default_matmul_precision or 'default'} "
          f"jax_compile_s={compile_s:.3f} jax_step_s={times[len(times) // 2]:.4f} "
          f"jax_min_step_s={times[0]:.4f} {memory}".rstrip())


DEFAULTS = {
    "xfactor-deep": dict(batch=1, height=48, width=48, patch_size=8, features=48, num_heads=3,
                         num_layers=3, pose_dim=24, global_tokens=4, context_views_mv=2, seed=1),
    "xfactor-manyviews": dict(batch=2, height=40, width=40, patch_size=5, features=64, num_heads=2,
                              num_layers=2, pose_dim=8, global_tokens=2, context_views_mv=5, seed=2),
}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    v = sub.add_parser("validate", help="compare this implementation against fixture files")
    v.add_argument("fixtures", nargs="+")
    v.add_argument("--out-tol", type=float, default=1e-4)
    v.add_argument("--grad-tol", type=float, default=1e-3)
    g = sub.add_parser("generate", help="generate one fixture")
    g.add_argument("name")
    g.add_argument("outdir")
    for k, dv in [("batch", 1), ("height", 32), ("width", 32), ("patch_size", 4), ("features", 64),
                  ("num_heads", 4), ("num_layers", 2), ("pose_dim", 16), ("global_tokens", 8),
                  ("context_views_mv", 3), ("seed", 0)]:
        g.add_argument("--" + k.replace("_", "-"), dest=k, type=int, default=dv)
    b = sub.add_parser("bench", help="time a jitted float32 stage-1 step (the peer of model_step)")
    for k, dv in [("batch", 8), ("height", 64), ("width", 64), ("patch_size", 8), ("features", 256),
                  ("num_heads", 8), ("num_layers", 4), ("pose_dim", 64), ("global_tokens", 8),
                  ("steps", 5), ("seed", 0)]:
        b.add_argument("--" + k.replace("_", "-"), dest=k, type=int, default=dv)
    gd = sub.add_parser("generate-defaults", help="generate xfactor-deep and xfactor-manyviews")
    gd.add_argument("outdir")
    a = ap.parse_args(argv)
    if a.cmd == "validate":
        ok = True
        for f in a.fixtures:
            oe, ge = compare(f)
            ok &= max(oe.values()) <= a.out_tol and max(ge.values()) <= a.grad_tol
        print("PASS" if ok else "FAIL")
        return 0 if ok else 1
    if a.cmd == "generate":
        cfg = {k: getattr(a, k) for k in ["batch", "height", "width", "patch_size", "features", "num_heads",
                                          "num_layers", "pose_dim", "global_tokens", "context_views_mv", "seed"]}
        generate(a.name, a.outdir, cfg)
        return 0
    if a.cmd == "bench":
        cfg = {k: getattr(a, k) for k in ["batch", "height", "width", "patch_size", "features", "num_heads",
                                          "num_layers", "pose_dim", "global_tokens", "seed"]}
        cfg["context_views_mv"] = 1
        bench(cfg, a.steps)
        return 0
    if a.cmd == "generate-defaults":
        for name, cfg in DEFAULTS.items():
            generate(name, a.outdir, cfg)
        return 0


if __name__ == "__main__":
    sys.exit(main())
