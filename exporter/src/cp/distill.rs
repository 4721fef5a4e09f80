//! A small batched trainer for [`Net`]s (hand-written backward pass,
//! Adam), used to distil CP factors towards a dense model's outputs
//! (`exporter cp --distill STEPS`) and to fit residual adapters with the
//! base frozen (the style demonstration).
//!
//! Loss: mean squared error of the normalised outputs (`(y - Ymean) / Ystd`),
//! so every output counts in units of its own spread.
//!
//! Distillation inputs are drawn from the dense model's normalisation
//! statistics and, with `--distill-data`, from rollouts of the float
//! controller (`host-sim rollout-dataset`: arrays [`DATA_INPUTS`] and
//! [`DATA_PHASES`] of an `.npz`), the inputs the controller actually feeds
//! the network.

use ndarray::{Array1, Array2, ArrayD, ArrayViewMutD, Axis, Zip};
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::io::samples::{normal_inputs, Samples};
use crate::net::{Adapter, Net, NetLayer};

/// Normalised inputs, gates and normalised targets of some samples.
#[derive(Clone, Debug)]
pub struct Dataset {
    /// `N x in`, normalised inputs.
    pub x: Array2<f64>,
    /// `N x K` gate weights (dense).
    pub g: Array2<f64>,
    /// `N x out` normalised targets.
    pub y: Array2<f64>,
}

impl Dataset {
    /// Rows `idx`.
    pub fn select(&self, idx: &[usize]) -> Dataset {
        Dataset {
            x: self.x.select(Axis(0), idx),
            g: self.g.select(Axis(0), idx),
            y: self.y.select(Axis(0), idx),
        }
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.x.nrows()
    }

    /// No samples.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Normalised inputs and the gate matrix of raw samples.
pub fn inputs_and_gates(net: &Net, xs: &[Vec<f64>], phases: &[f64]) -> (Array2<f64>, Array2<f64>) {
    let (n, d, k) = (xs.len(), net.input_dim(), net.experts());
    let mut x = Array2::zeros((n, d));
    let mut g = Array2::zeros((n, k));
    for (i, (raw, &p)) in xs.iter().zip(phases).enumerate() {
        for j in 0..d {
            x[(i, j)] = (raw[j] - net.xmean[j]) / net.xstd[j];
        }
        for (e, w) in net.gate(p) {
            g[(i, e)] += w;
        }
    }
    (x, g)
}

/// A CP layer's `X B` and blended cores `G D` of a batch.
type CpCache = Option<(Array2<f64>, Array2<f64>)>;

/// Per-layer cache of a batched forward pass.
struct Cache {
    /// Input of the layer.
    x: Array2<f64>,
    /// Pre-activation (adapters included).
    pre: Array2<f64>,
    /// CP: `X B` and the blended cores `G D`.
    cp: CpCache,
}

fn bias_matrix(b: &[Array1<f64>]) -> Array2<f64> {
    let out = b.first().map_or(0, Array1::len);
    Array2::from_shape_fn((b.len(), out), |(k, i)| b[k][i])
}

/// Batched `y = layer(x)` with per-sample gates `g` (`N x K`); for CP layers
/// also `X B` and `G D`.
fn layer_forward(layer: &NetLayer, x: &Array2<f64>, g: &Array2<f64>) -> (Array2<f64>, CpCache) {
    let g = if layer.experts() == 1 {
        Array2::ones((x.nrows(), 1))
    } else {
        g.clone()
    };
    match layer {
        NetLayer::Dense(l) => {
            let mut y = g.dot(&bias_matrix(&l.b));
            for (k, w) in l.w.iter().enumerate() {
                let xw = x.dot(&w.t());
                y += &(&xw * &g.column(k).insert_axis(Axis(1)));
            }
            (y, None)
        }
        NetLayer::Cp(l) => {
            let u0 = x.dot(&l.b);
            let cb = g.dot(&l.d);
            let y = (&u0 * &cb).dot(&l.a.t()) + g.dot(&bias_matrix(&l.bias));
            (y, Some((u0, cb)))
        }
        NetLayer::Diagonal(l) => {
            let gw = g.dot(&bias_matrix(&l.w));
            (&gw * x + g.dot(&bias_matrix(&l.b)), None)
        }
        NetLayer::Rbf(_) | NetLayer::Dec(_) => (rows_apply(layer, x, &g), None),
    }
}

/// A layer's pre-activation sample by sample (rows of `x`, gate
/// coefficients in the rows of `g`): for ops with no matrix form.
pub(crate) fn rows_apply(layer: &NetLayer, x: &Array2<f64>, g: &Array2<f64>) -> Array2<f64> {
    let mut y = Array2::zeros((x.nrows(), layer.out_dim()));
    for ((xr, gr), mut yr) in x.rows().into_iter().zip(g.rows()).zip(y.rows_mut()) {
        let gate: Vec<(usize, f64)> = gr.iter().copied().enumerate().collect();
        yr.assign(&layer.apply(&gate, &xr.to_owned()));
    }
    y
}

/// Gradients of a layer's parameters, in [`params_mut`] order, and `dX`.
fn layer_backward(
    layer: &NetLayer,
    x: &Array2<f64>,
    g: &Array2<f64>,
    cp: Option<&(Array2<f64>, Array2<f64>)>,
    dy: &Array2<f64>,
    want_params: bool,
) -> (Array2<f64>, Vec<ArrayD<f64>>) {
    let g = if layer.experts() == 1 {
        Array2::ones((x.nrows(), 1))
    } else {
        g.clone()
    };
    let rows = |m: Array2<f64>| -> Vec<ArrayD<f64>> {
        m.rows()
            .into_iter()
            .map(|r| r.to_owned().into_dyn())
            .collect()
    };
    match (layer, cp) {
        (NetLayer::Dense(l), _) => {
            let mut dx = Array2::zeros(x.dim());
            let mut grads = Vec::new();
            for (k, w) in l.w.iter().enumerate() {
                let gdy = dy * &g.column(k).insert_axis(Axis(1));
                dx += &gdy.dot(w);
                if want_params {
                    grads.push(gdy.t().dot(x).into_dyn());
                }
            }
            if want_params {
                grads.extend(rows(g.t().dot(dy)));
            }
            (dx, grads)
        }
        (NetLayer::Cp(l), Some((u0, cb))) => {
            let du = dy.dot(&l.a);
            let du0 = &du * cb;
            let dx = du0.dot(&l.b.t());
            if !want_params {
                return (dx, Vec::new());
            }
            let u = u0 * cb;
            let da = dy.t().dot(&u);
            let dd = g.t().dot(&(&du * u0));
            let db = x.t().dot(&du0);
            let mut grads = vec![da.into_dyn(), db.into_dyn(), dd.into_dyn()];
            grads.extend(rows(g.t().dot(dy)));
            (dx, grads)
        }
        (NetLayer::Diagonal(l), _) => {
            let gw = g.dot(&bias_matrix(&l.w));
            let dx = dy * &gw;
            if !want_params {
                return (dx, Vec::new());
            }
            let mut grads = rows(g.t().dot(&(dy * x)));
            grads.extend(rows(g.t().dot(dy)));
            (dx, grads)
        }
        (NetLayer::Cp(_), None) => (Array2::zeros(x.dim()), Vec::new()),
        // d psi_j / dx = -2 sigma_j^2 (x - c_j) psi_j; its centres and
        // widths are not distilled (no parameters, see `params_mut`).
        (NetLayer::Rbf(l), _) => {
            let mut dx = Array2::zeros(x.dim());
            for (s, (xr, mut dxr)) in x.rows().into_iter().zip(dx.rows_mut()).enumerate() {
                for (k, gk) in g.row(s).iter().enumerate() {
                    for (j, c) in l.centres[k].rows().into_iter().enumerate() {
                        let diff = &xr - &c;
                        let s2 = l.sigma[k][j].powi(2);
                        let psi = (-s2 * diff.dot(&diff)).exp();
                        dxr.scaled_add(-2.0 * s2 * psi * gk * dy[[s, j]], &diff);
                    }
                }
            }
            (dx, Vec::new())
        }
        // Its centres are not distilled either (see `params_mut`).
        (NetLayer::Dec(l), _) => {
            let mut dx = Array2::zeros(x.dim());
            for (s, (xr, mut dxr)) in x.rows().into_iter().zip(dx.rows_mut()).enumerate() {
                let gate: Vec<(usize, f64)> = g.row(s).iter().copied().enumerate().collect();
                dxr += &l.backward(&gate, &xr.to_owned(), &dy.row(s).to_owned());
            }
            (dx, Vec::new())
        }
    }
}

/// The parameters of a layer as mutable views, in a fixed order.
fn params_mut(layer: &mut NetLayer) -> Vec<ArrayViewMutD<'_, f64>> {
    match layer {
        NetLayer::Dense(l) => {
            l.w.iter_mut()
                .map(|w| w.view_mut().into_dyn())
                .chain(l.b.iter_mut().map(|b| b.view_mut().into_dyn()))
                .collect()
        }
        NetLayer::Cp(l) => [
            l.a.view_mut().into_dyn(),
            l.b.view_mut().into_dyn(),
            l.d.view_mut().into_dyn(),
        ]
        .into_iter()
        .chain(l.bias.iter_mut().map(|b| b.view_mut().into_dyn()))
        .collect(),
        NetLayer::Diagonal(l) => {
            l.w.iter_mut()
                .map(|w| w.view_mut().into_dyn())
                .chain(l.b.iter_mut().map(|b| b.view_mut().into_dyn()))
                .collect()
        }
        NetLayer::Rbf(_) | NetLayer::Dec(_) => Vec::new(),
    }
}

fn elu_grad(pre: &Array2<f64>) -> Array2<f64> {
    pre.mapv(|v| if v > 0.0 { 1.0 } else { v.exp() })
}

/// Batched forward pass; returns the normalised outputs and the caches.
fn forward(
    net: &Net,
    adapters: &[(&Adapter, f64)],
    x: &Array2<f64>,
    g: &Array2<f64>,
) -> (Array2<f64>, Vec<Cache>, Vec<Vec<CpCache>>) {
    let last = net.layers.len() - 1;
    let mut h = x.clone();
    let mut caches = Vec::new();
    let mut ad_caches = Vec::new();
    for (l, layer) in net.layers.iter().enumerate() {
        let (mut pre, cp) = layer_forward(layer, &h, g);
        let mut ac = Vec::new();
        for (ad, w) in adapters {
            if ad.layer == l {
                let (r, c) = layer_forward(&ad.op, &h, g);
                pre.scaled_add(*w, &r);
                ac.push(c);
            } else {
                ac.push(None);
            }
        }
        let next = if l == last {
            pre.clone()
        } else {
            pre.mapv(crate::net::elu)
        };
        caches.push(Cache { x: h, pre, cp });
        ad_caches.push(ac);
        h = next;
    }
    (h, caches, ad_caches)
}

/// Adam state of one parameter list.
struct Adam {
    m: Vec<ArrayD<f64>>,
    v: Vec<ArrayD<f64>>,
}

impl Adam {
    fn new(params: &[ArrayViewMutD<'_, f64>]) -> Adam {
        Adam {
            m: params.iter().map(|p| ArrayD::zeros(p.raw_dim())).collect(),
            v: params.iter().map(|p| ArrayD::zeros(p.raw_dim())).collect(),
        }
    }

    fn step(
        &mut self,
        params: &mut [ArrayViewMutD<'_, f64>],
        grads: &[ArrayD<f64>],
        lr: f64,
        t: i32,
        l1: f64,
    ) {
        let (b1, b2, eps) = (0.9f64, 0.999f64, 1e-8);
        let (c1, c2) = (1.0 - b1.powi(t), 1.0 - b2.powi(t));
        for ((p, g), (m, v)) in params
            .iter_mut()
            .zip(grads)
            .zip(self.m.iter_mut().zip(self.v.iter_mut()))
        {
            Zip::from(p).and(g).and(m).and(v).for_each(|p, &g, m, v| {
                let g = g + l1 * p.signum();
                *m = b1 * *m + (1.0 - b1) * g;
                *v = b2 * *v + (1.0 - b2) * g * g;
                *p -= lr * (*m / c1) / ((*v / c2).sqrt() + eps);
            });
        }
    }
}

/// Knobs of [`train`].
#[derive(Clone, Debug, Serialize)]
pub struct TrainOptions {
    /// Adam steps.
    pub steps: usize,
    /// Minibatch size.
    pub batch: usize,
    /// Learning rate (cosine-decayed to 10% over the steps).
    pub lr: f64,
    /// L1 penalty on the trained parameters (the paper uses 0.01 in its
    /// loss; applied here per parameter, scaled by the batch loss's size).
    pub l1: f64,
    /// Seed of the minibatch order.
    pub seed: u64,
}

impl Default for TrainOptions {
    fn default() -> Self {
        TrainOptions {
            steps: 500,
            batch: 64,
            lr: 1e-3,
            l1: 0.0,
            seed: 0xD15_7111,
        }
    }
}

/// Loss curve of a run.
#[derive(Clone, Debug, Default, Serialize)]
pub struct TrainReport {
    /// Mean squared normalised error on the whole data set, before.
    pub loss_before: f64,
    /// After.
    pub loss_after: f64,
    /// Minibatch loss every 10% of the steps.
    pub curve: Vec<(usize, f64)>,
}

/// Mean squared error of `net` (with adapters) on `data`.
pub fn loss(net: &Net, adapters: &[(&Adapter, f64)], data: &Dataset) -> f64 {
    let mut total = 0.0;
    let n = data.len();
    for start in (0..n).step_by(256) {
        let idx: Vec<usize> = (start..(start + 256).min(n)).collect();
        let b = data.select(&idx);
        let (y, _, _) = forward(net, adapters, &b.x, &b.g);
        total += (&y - &b.y).mapv(|v| v * v).sum();
    }
    total / (n.max(1) * data.y.ncols().max(1)) as f64
}

/// Trains the layers `train_layers` of `net` and every adapter in
/// `adapters` (weight 1 each) on `data`; everything else stays frozen.
pub fn train(
    net: &mut Net,
    train_layers: &[usize],
    adapters: &mut [Adapter],
    data: &Dataset,
    opts: &TrainOptions,
) -> TrainReport {
    let mut rng = ChaCha8Rng::seed_from_u64(opts.seed);
    let mut report = TrainReport {
        loss_before: {
            let ads: Vec<(&Adapter, f64)> = adapters.iter().map(|a| (a, 1.0)).collect();
            loss(net, &ads, data)
        },
        ..TrainReport::default()
    };
    let mut layer_adam: Vec<Adam> = train_layers
        .iter()
        .map(|&l| Adam::new(&params_mut(&mut net.layers[l])))
        .collect();
    let mut ad_adam: Vec<Adam> = adapters
        .iter_mut()
        .map(|a| Adam::new(&params_mut(&mut a.op)))
        .collect();
    let mut order: Vec<usize> = (0..data.len()).collect();
    let mut pos = order.len();
    let last = net.layers.len() - 1;
    let every = (opts.steps / 10).max(1);
    for step in 0..opts.steps {
        if pos + opts.batch > order.len() {
            order.shuffle(&mut rng);
            pos = 0;
        }
        let idx = &order[pos..(pos + opts.batch).min(order.len())];
        pos += opts.batch;
        let b = data.select(idx);
        let (layer_grads, ad_grads, batch_loss) = {
            let ads: Vec<(&Adapter, f64)> = adapters.iter().map(|a| (a, 1.0)).collect();
            let (y, caches, ad_caches) = forward(net, &ads, &b.x, &b.g);
            let diff = &y - &b.y;
            let scale = 2.0 / (diff.len().max(1)) as f64;
            let batch_loss = diff.mapv(|v| v * v).mean().unwrap_or(0.0);
            let mut dh = diff * scale;
            let first_trained = train_layers
                .iter()
                .copied()
                .chain(adapters.iter().map(|a| a.layer))
                .min()
                .unwrap_or(0);
            let mut layer_grads = vec![Vec::new(); net.layers.len()];
            let mut ad_grads = vec![Vec::new(); adapters.len()];
            for l in (first_trained..=last).rev() {
                let c = &caches[l];
                let dpre = if l == last {
                    dh.clone()
                } else {
                    dh * &elu_grad(&c.pre)
                };
                let want = train_layers.contains(&l);
                let need_dx = l > first_trained;
                let (mut dx, grads) = if want || need_dx {
                    layer_backward(&net.layers[l], &c.x, &b.g, c.cp.as_ref(), &dpre, want)
                } else {
                    (Array2::zeros(c.x.dim()), Vec::new())
                };
                layer_grads[l] = grads;
                for (ai, ad) in adapters.iter().enumerate() {
                    if ad.layer == l {
                        let (adx, g) = layer_backward(
                            &ad.op,
                            &c.x,
                            &b.g,
                            ad_caches[l][ai].as_ref(),
                            &dpre,
                            true,
                        );
                        ad_grads[ai] = g;
                        if need_dx {
                            dx += &adx;
                        }
                    }
                }
                dh = dx;
            }
            (layer_grads, ad_grads, batch_loss)
        };
        let t = step as i32 + 1;
        let progress = step as f64 / opts.steps.max(1) as f64;
        let lr = opts.lr * (0.1 + 0.9 * 0.5 * (1.0 + (std::f64::consts::PI * progress).cos()));
        for (adam, &l) in layer_adam.iter_mut().zip(train_layers) {
            let mut p = params_mut(&mut net.layers[l]);
            adam.step(&mut p, &layer_grads[l], lr, t, opts.l1);
        }
        for (ai, (adam, ad)) in ad_adam.iter_mut().zip(adapters.iter_mut()).enumerate() {
            let mut p = params_mut(&mut ad.op);
            adam.step(&mut p, &ad_grads[ai], lr, t, opts.l1);
        }
        if step % every == 0 || step + 1 == opts.steps {
            report.curve.push((step, batch_loss));
        }
    }
    let ads: Vec<(&Adapter, f64)> = adapters.iter().map(|a| (a, 1.0)).collect();
    report.loss_after = loss(net, &ads, data);
    report
}

/// Knobs of [`distill`].
#[derive(Clone, Debug, Serialize)]
pub struct DistillOptions {
    /// Adam steps.
    pub steps: usize,
    /// Size of the training set: normal samples and rollout rows together.
    pub samples: usize,
    /// Share of the training set drawn from the normalisation statistics
    /// when rollout data is given (the rest are rollout rows); without
    /// rollout data every sample is a normal one.
    pub normal_fraction: f64,
    /// Spread of the normal samples (`mean + std N(0,1) spread`).
    pub spread: f64,
    /// Minibatch.
    pub batch: usize,
    /// Learning rate.
    pub lr: f64,
    /// Seed.
    pub seed: u64,
}

/// Default of [`DistillOptions::normal_fraction`] (`--distill-normal-fraction`).
pub const DEFAULT_NORMAL_FRACTION: f64 = 0.5;

impl Default for DistillOptions {
    fn default() -> Self {
        DistillOptions {
            steps: 1000,
            samples: 4096,
            normal_fraction: DEFAULT_NORMAL_FRACTION,
            spread: 1.0,
            batch: 64,
            lr: 3e-4,
            seed: 0xD157,
        }
    }
}

use crate::io::samples::{extend, pick};
pub use crate::io::samples::{
    held_out_split, read_distill_data, DistillData, DATA_INPUTS, DATA_PHASES, HELD_OUT_BLOCK,
    HELD_OUT_EVERY,
};

/// Mean squared normalised output error on one held-out set.
#[derive(Clone, Debug, Serialize)]
pub struct HeldOutLoss {
    /// What the set is.
    pub name: String,
    /// Its rows.
    pub rows: usize,
    /// Before distillation.
    pub before: f64,
    /// After.
    pub after: f64,
}

/// What distillation did.
#[derive(Clone, Debug, Serialize)]
pub struct DistillReport {
    /// Options used.
    pub options: DistillOptions,
    /// Normal samples in the training set.
    pub normal_samples: usize,
    /// Rollout rows in the training set (repeats included).
    pub rollout_samples: usize,
    /// Distinct rollout training rows available.
    pub rollout_rows: usize,
    /// Losses (mean squared normalised output error on the training set).
    pub train: TrainReport,
    /// The same on 512 fresh normal samples, before and after.
    pub held_out_before: f64,
    /// After.
    pub held_out_after: f64,
    /// The same on the held-out rollout rows, if rollout data was given.
    pub rollout_held_out: Option<HeldOutLoss>,
    /// The same on each evaluation-only set.
    pub eval: Vec<HeldOutLoss>,
}

/// The dense model's normalised outputs on raw samples, as a data set for `net`.
pub fn teacher_dataset(dense: &Net, net: &Net, xs: &[Vec<f64>], phases: &[f64]) -> Dataset {
    let (x, g) = inputs_and_gates(net, xs, phases);
    let mut y = Array2::zeros((xs.len(), dense.output_dim()));
    for (i, (raw, &p)) in xs.iter().zip(phases).enumerate() {
        let t = dense.forward_trace(raw, p);
        let y_norm = t.pre.last().map(|p| p.to_vec()).unwrap_or_default();
        for (j, v) in y_norm.iter().enumerate() {
            y[(i, j)] = *v;
        }
    }
    Dataset { x, g, y }
}

/// How many of `samples` training samples are rollout rows.
pub fn rollout_share(samples: usize, normal_fraction: f64, rollout_rows: usize) -> usize {
    if rollout_rows == 0 {
        return 0;
    }
    let f = normal_fraction.clamp(0.0, 1.0);
    ((1.0 - f) * samples as f64).round() as usize
}

/// Fine-tunes the CP layers of `net` (dense layers stay as they are) so its
/// outputs match `dense`'s on a training set of `opts.samples` inputs: a
/// share `opts.normal_fraction` drawn from the normalisation statistics,
/// the rest rows of `data.train` (each row used equally often, +-1; all
/// normal samples when `data.train` is empty). Losses are reported on 512
/// fresh normal samples, on `data.held_out` and on every `data.eval` set.
pub fn distill(
    dense: &Net,
    net: &Net,
    data: &DistillData,
    opts: &DistillOptions,
) -> (Net, DistillReport) {
    let stats = (dense.xmean.to_vec(), dense.xstd.to_vec());
    let n_roll = rollout_share(opts.samples, opts.normal_fraction, data.train.inputs.len());
    let n_norm = opts.samples - n_roll.min(opts.samples);
    let mut s = normal_inputs(&stats.0, &stats.1, n_norm, opts.spread, opts.seed);
    if n_roll > 0 {
        let mut perm: Vec<usize> = (0..data.train.inputs.len()).collect();
        perm.shuffle(&mut ChaCha8Rng::seed_from_u64(opts.seed ^ 0x5A5A));
        let idx: Vec<usize> = (0..n_roll).map(|i| perm[i % perm.len()]).collect();
        extend(&mut s, pick(&data.train, &idx));
    }
    let held = normal_inputs(&stats.0, &stats.1, 512, opts.spread, opts.seed ^ 0xFFFF);
    let train_set = teacher_dataset(dense, net, &s.inputs, &s.phases);
    let teacher = |s: &Samples| teacher_dataset(dense, net, &s.inputs, &s.phases);
    let held = teacher(&held);
    let mut sets: Vec<(String, Dataset)> = Vec::new();
    if !data.held_out.inputs.is_empty() {
        sets.push(("rollout rows held out".into(), teacher(&data.held_out)));
    }
    for (name, e) in &data.eval {
        sets.push((name.clone(), teacher(e)));
    }
    let mut tuned = net.clone();
    let layers: Vec<usize> = tuned
        .layers
        .iter()
        .enumerate()
        .filter(|(_, l)| matches!(l, NetLayer::Cp(_)))
        .map(|(i, _)| i)
        .collect();
    let held_out_before = loss(&tuned, &[], &held);
    let before: Vec<f64> = sets.iter().map(|(_, d)| loss(&tuned, &[], d)).collect();
    let train_report = train(
        &mut tuned,
        &layers,
        &mut [],
        &train_set,
        &TrainOptions {
            steps: opts.steps,
            batch: opts.batch,
            lr: opts.lr,
            l1: 0.0,
            seed: opts.seed,
        },
    );
    let held_out_after = loss(&tuned, &[], &held);
    let mut losses = sets
        .iter()
        .zip(before)
        .map(|((name, d), before)| HeldOutLoss {
            name: name.clone(),
            rows: d.len(),
            before,
            after: loss(&tuned, &[], d),
        })
        .collect::<Vec<_>>()
        .into_iter();
    let rollout_held_out = if data.held_out.inputs.is_empty() {
        None
    } else {
        losses.next()
    };
    (
        tuned,
        DistillReport {
            options: opts.clone(),
            normal_samples: n_norm,
            rollout_samples: n_roll,
            rollout_rows: data.train.inputs.len(),
            train: train_report,
            held_out_before,
            held_out_after,
            rollout_held_out,
            eval: losses.collect(),
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::net::{CpLayer, DiagLayer};
    use crate::net::{ExpertLayer, GatingMode};
    use rand::Rng;

    fn rnd(rng: &mut ChaCha8Rng, r: usize, c: usize, sd: f64) -> Array2<f64> {
        Array2::from_shape_fn((r, c), |_| rng.gen_range(-1.0..1.0) * sd)
    }

    fn tiny(rng: &mut ChaCha8Rng) -> Net {
        let dense = |rng: &mut ChaCha8Rng, o: usize, i: usize| {
            NetLayer::Dense(ExpertLayer {
                w: (0..4).map(|_| rnd(rng, o, i, 0.5)).collect(),
                b: (0..4)
                    .map(|_| rnd(rng, 1, o, 0.1).row(0).to_owned())
                    .collect(),
            })
        };
        Net {
            mode: GatingMode::Cubic,
            xmean: Array1::zeros(5),
            xstd: Array1::ones(5),
            ymean: Array1::zeros(3),
            ystd: Array1::ones(3),
            layers: vec![
                dense(rng, 6, 5),
                NetLayer::Cp(CpLayer {
                    a: rnd(rng, 6, 3, 0.5),
                    b: rnd(rng, 6, 3, 0.5),
                    d: rnd(rng, 4, 3, 1.0),
                    bias: (0..4)
                        .map(|_| rnd(rng, 1, 6, 0.1).row(0).to_owned())
                        .collect(),
                }),
                dense(rng, 3, 6),
            ],
            wiring: crate::net::Wiring::Chain,
        }
    }

    /// The hand-written gradients agree with finite differences, for every
    /// layer form and for adapters.
    #[test]
    fn gradients_match_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let net = tiny(&mut rng);
        let xs: Vec<Vec<f64>> = (0..7)
            .map(|_| (0..5).map(|_| rng.gen_range(-2.0..2.0)).collect())
            .collect();
        let ps: Vec<f64> = (0..7)
            .map(|_| rng.gen_range(0.0..std::f64::consts::TAU))
            .collect();
        let (x, g) = inputs_and_gates(&net, &xs, &ps);
        let data = Dataset {
            x,
            g,
            y: rnd(&mut rng, 7, 3, 1.0),
        };
        let adapters = vec![
            Adapter {
                layer: 1,
                op: NetLayer::Diagonal(DiagLayer {
                    w: (0..4)
                        .map(|_| rnd(&mut rng, 1, 6, 0.3).row(0).to_owned())
                        .collect(),
                    b: (0..4)
                        .map(|_| rnd(&mut rng, 1, 6, 0.3).row(0).to_owned())
                        .collect(),
                }),
            },
            Adapter {
                layer: 1,
                op: NetLayer::Cp(CpLayer {
                    a: rnd(&mut rng, 6, 2, 0.5),
                    b: rnd(&mut rng, 6, 2, 0.5),
                    d: rnd(&mut rng, 4, 2, 1.0),
                    bias: (0..4).map(|_| Array1::zeros(6)).collect(),
                }),
            },
        ];
        // Analytic gradients through one zero-learning-rate "step": use
        // the internals directly.
        let ads: Vec<(&Adapter, f64)> = adapters.iter().map(|a| (a, 1.0)).collect();
        let (y, caches, ad_caches) = forward(&net, &ads, &data.x, &data.g);
        let diff = &y - &data.y;
        let scale = 2.0 / diff.len() as f64;
        let dpre2 = diff * scale;
        let (dh1, g2) = layer_backward(&net.layers[2], &caches[2].x, &data.g, None, &dpre2, true);
        let dpre1 = dh1 * &elu_grad(&caches[1].pre);
        let (dh0, g1) = layer_backward(
            &net.layers[1],
            &caches[1].x,
            &data.g,
            caches[1].cp.as_ref(),
            &dpre1,
            true,
        );
        let (dxa0, ga0) =
            layer_backward(&adapters[0].op, &caches[1].x, &data.g, None, &dpre1, true);
        let (dxa1, ga1) = layer_backward(
            &adapters[1].op,
            &caches[1].x,
            &data.g,
            ad_caches[1][1].as_ref(),
            &dpre1,
            true,
        );
        let dpre0 = (dh0 + dxa0 + dxa1) * &elu_grad(&caches[0].pre);
        let (_, g0) = layer_backward(&net.layers[0], &caches[0].x, &data.g, None, &dpre0, true);
        let check = |analytic: &[ArrayD<f64>], perturb: &dyn Fn(usize, usize, f64) -> f64| {
            for (pi, a) in analytic.iter().enumerate() {
                for (ei, &av) in a.iter().enumerate().step_by(3) {
                    let h = 1e-6;
                    let num = (perturb(pi, ei, h) - perturb(pi, ei, -h)) / (2.0 * h);
                    assert!(
                        (num - av).abs() <= 1e-6 + 1e-4 * num.abs(),
                        "param {pi}[{ei}]: {num} vs {av}"
                    );
                }
            }
        };
        for (l, grads) in [(0usize, &g0), (1, &g1), (2, &g2)] {
            check(grads, &|pi, ei, h| {
                let mut n2 = net.clone();
                let mut p = params_mut(&mut n2.layers[l]);
                let v = p[pi].iter_mut().nth(ei).unwrap();
                *v += h;
                drop(p);
                loss(&n2, &ads, &data)
            });
        }
        for (ai, grads) in [(0usize, &ga0), (1, &ga1)] {
            check(grads, &|pi, ei, h| {
                let mut a2 = adapters.clone();
                let mut p = params_mut(&mut a2[ai].op);
                let v = p[pi].iter_mut().nth(ei).unwrap();
                *v += h;
                drop(p);
                let ads: Vec<(&Adapter, f64)> = a2.iter().map(|a| (a, 1.0)).collect();
                loss(&net, &ads, &data)
            });
        }
    }

    #[test]
    fn batched_forward_equals_the_float_reference() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let net = tiny(&mut rng);
        let xs: Vec<Vec<f64>> = (0..5)
            .map(|_| (0..5).map(|_| rng.gen_range(-2.0..2.0)).collect())
            .collect();
        let ps: Vec<f64> = (0..5)
            .map(|_| rng.gen_range(0.0..std::f64::consts::TAU))
            .collect();
        let (x, g) = inputs_and_gates(&net, &xs, &ps);
        let (y, _, _) = forward(&net, &[], &x, &g);
        for (i, (raw, &p)) in xs.iter().zip(&ps).enumerate() {
            let want = net.forward(raw, p);
            for j in 0..3 {
                assert!((y[(i, j)] - want[j]).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn training_lowers_the_loss() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut net = tiny(&mut rng);
        let xs: Vec<Vec<f64>> = (0..256)
            .map(|_| (0..5).map(|_| rng.gen_range(-2.0..2.0)).collect())
            .collect();
        let ps: Vec<f64> = (0..256)
            .map(|_| rng.gen_range(0.0..std::f64::consts::TAU))
            .collect();
        let (x, g) = inputs_and_gates(&net, &xs, &ps);
        let target = tiny(&mut rng);
        let y = target.outputs(&xs, &ps);
        let data = Dataset { x, g, y };
        let rep = train(
            &mut net,
            &[1],
            &mut [],
            &data,
            &TrainOptions {
                steps: 300,
                lr: 1e-2,
                ..TrainOptions::default()
            },
        );
        assert!(rep.loss_after < 0.8 * rep.loss_before, "{rep:?}");
    }

    #[test]
    fn rollout_share_takes_the_normal_fraction_from_the_samples() {
        assert_eq!(rollout_share(100, 0.25, 10), 75);
        assert_eq!(rollout_share(100, 0.25, 0), 0);
        assert_eq!(rollout_share(100, 1.0, 10), 0);
    }
}
