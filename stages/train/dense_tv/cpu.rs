//! FISTA on the CPU, in f32 with rayon: each step projects the look-ahead point, back-projects
//! its residual, then one pass over z-slabs takes the TV's gradient, the step and the next
//! look-ahead together. Its sums (the change, the restart test) are per slab, added in slab
//! order, so a solve is the same whatever the thread count.

use super::tv::{self, PlaneDirections};
use super::{next_momentum, DenseProblem, FistaSolver, Stop};
use crate::train::regularize::lane_sum;
use rayon::prelude::*;

/// z-planes per task of the step's pass.
const PLANES_PER_TASK: usize = 4;

/// The solver's buffers, reused from step to step.
pub struct CpuFista {
    ahead: Vec<f32>,
    ahead_next: Vec<f32>,
    back: Vec<f32>,
    depths: Vec<f64>,
    residual: Vec<f64>,
    /// Per task of the step's pass.
    scratch: Vec<TaskScratch>,
}

/// A task's `p` on its current plane and the one below, and a row's terms.
struct TaskScratch {
    below: PlaneDirections,
    at: PlaneDirections,
    gradient: Vec<f32>,
    curvature: Vec<f32>,
    /// Each node's `(σ' − σ)²`, `σ'²` and share of the restart test.
    change: Vec<f32>,
    norm: Vec<f32>,
    uphill: Vec<f32>,
}

impl TaskScratch {
    fn new(n: usize) -> TaskScratch {
        TaskScratch {
            below: PlaneDirections::new(n),
            at: PlaneDirections::new(n),
            gradient: vec![0.0; n],
            curvature: vec![0.0; n],
            change: vec![0.0; n],
            norm: vec![0.0; n],
            uphill: vec![0.0; n],
        }
    }
}

/// What a step's pass adds up: `Σ (σ' − σ)²`, `Σ σ'²`, and the restart test
/// `Σ (σ̂ − σ')(σ' − σ) / step` (positive when the momentum points uphill; O'Donoghue and
/// Candès's gradient test in the steps' metric).
#[derive(Default, Clone, Copy)]
struct StepSums {
    change: f64,
    norm: f64,
    uphill: f64,
}

impl CpuFista {
    pub fn new(problem: &DenseProblem) -> CpuFista {
        let (n, nodes) = (problem.n, problem.nodes());
        let tasks = n.div_ceil(PLANES_PER_TASK);
        CpuFista {
            ahead: vec![0.0; nodes],
            ahead_next: vec![0.0; nodes],
            back: vec![0.0; nodes],
            depths: vec![0.0; problem.projector.rays],
            residual: vec![0.0; problem.projector.rays],
            scratch: (0..tasks).map(|_| TaskScratch::new(n)).collect(),
        }
    }

    /// The TV gradient, the projected step from the look-ahead point and the next look-ahead
    /// point (momentum `momentum`), writing σ and `ahead_next`.
    fn step_pass(&mut self, problem: &DenseProblem, sigma: &mut [f32], momentum: f32) -> StepSums {
        let n = problem.n;
        let per_task = PLANES_PER_TASK * n * n;
        let per_ray = (1.0 / problem.rays_seen) as f32;
        let tv_weight = (problem.lambda / problem.nodes() as f64) as f32;
        let epsilon = problem.epsilon as f32;
        let (ahead, back, data_curvature) = (&self.ahead, &self.back, &problem.data_curvature);
        let sums: Vec<StepSums> = sigma
            .par_chunks_mut(per_task)
            .zip(self.ahead_next.par_chunks_mut(per_task))
            .zip(self.scratch.par_iter_mut())
            .enumerate()
            .map(|(task, ((sigma, ahead_next), scratch))| {
                let z0 = task * PLANES_PER_TASK;
                if z0 > 0 {
                    scratch.below.compute(ahead, n, z0 - 1, epsilon);
                }
                let mut sums = StepSums::default();
                for (dz, (sigma, ahead_next)) in sigma.chunks_mut(n * n).zip(ahead_next.chunks_mut(n * n)).enumerate() {
                    let z = z0 + dz;
                    let s = &mut *scratch;
                    s.at.compute(ahead, n, z, epsilon);
                    let mut plane = [0.0f32; 3];
                    for y in 0..n {
                        tv::row_terms(&s.at, (z > 0).then_some(&s.below), n, y, &mut s.gradient, &mut s.curvature);
                        let (at, row) = (z * n * n + y * n, y * n..(y + 1) * n);
                        let (ahead, back, data_curvature) =
                            (&ahead[at..at + n], &back[at..at + n], &data_curvature[at..at + n]);
                        let (sigma, ahead_next) = (&mut sigma[row.clone()], &mut ahead_next[row]);
                        let (tv_gradient, tv_curvature) = (&s.gradient[..n], &s.curvature[..n]);
                        let (changes, norms, uphills) = (&mut s.change[..n], &mut s.norm[..n], &mut s.uphill[..n]);
                        for x in 0..n {
                            let g = back[x] * per_ray + tv_weight * tv_gradient[x];
                            let curvature = data_curvature[x] + tv_weight * tv_curvature[x];
                            let next = (ahead[x] - g / curvature).max(0.0);
                            let change = next - sigma[x];
                            changes[x] = change * change;
                            norms[x] = next * next;
                            uphills[x] = (ahead[x] - next) * change * curvature;
                            ahead_next[x] = next + momentum * change;
                            sigma[x] = next;
                        }
                        plane[0] += lane_sum(changes, |v| v);
                        plane[1] += lane_sum(norms, |v| v);
                        plane[2] += lane_sum(uphills, |v| v);
                    }
                    sums.change += f64::from(plane[0]);
                    sums.norm += f64::from(plane[1]);
                    sums.uphill += f64::from(plane[2]);
                    std::mem::swap(&mut s.below, &mut s.at);
                }
                sums
            })
            .collect();
        sums.iter().fold(StepSums::default(), |a, s| StepSums {
            change: a.change + s.change,
            norm: a.norm + s.norm,
            uphill: a.uphill + s.uphill,
        })
    }
}

impl FistaSolver for CpuFista {
    fn solve(
        &mut self,
        problem: &DenseProblem,
        sigma: &mut [f32],
        stop: Stop,
        wants: &dyn Fn(usize) -> bool,
        checkpoint: &mut dyn FnMut(usize, &[f32]),
    ) -> anyhow::Result<usize> {
        self.ahead.copy_from_slice(sigma);
        let mut t = 1.0f64;
        // Whether this step's look-ahead carries momentum. A step from σ itself (the first two,
        // and the two after a restart) is a plain projected gradient step, which on this
        // ill-conditioned E changes σ far less than the distance left to the minimum: only a
        // coasting step may end the solve.
        let mut coasting = false;
        for step in 1..=stop.steps {
            problem.projector.project(&self.ahead, &mut self.depths);
            problem.residual_into(&self.depths, &mut self.residual);
            problem.projector.back_project(&self.residual, &mut self.back);
            let (t_next, momentum) = next_momentum(t);
            let sums = self.step_pass(problem, sigma, momentum as f32);
            std::mem::swap(&mut self.ahead, &mut self.ahead_next);
            t = t_next;
            let coasted = std::mem::replace(&mut coasting, momentum > 0.0);
            if sums.uphill > 0.0 {
                // Adaptive restart: the momentum carried σ uphill, so start it again from σ.
                t = 1.0;
                self.ahead.copy_from_slice(sigma);
                coasting = false;
            }
            let settled = coasted && (sums.change / sums.norm.max(f64::MIN_POSITIVE)).sqrt() <= stop.tolerance;
            if wants(step) || settled || step == stop.steps {
                checkpoint(step, sigma);
            }
            if settled {
                return Ok(step);
            }
        }
        Ok(stop.steps)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_a_step_that_carries_momentum_ends_the_solve() {
        // Every ray sees nothing (I = 1), so σ = 0 is the minimum and no step moves it: the
        // first step that may end the solve is the third, the first whose look-ahead coasts.
        let (lattice, rays) = super::super::ring_of_rays(1.0);
        let problem = DenseProblem::new(&lattice, 1.0, 1e-2, 1e-3, &rays, &[(30, 30)]);
        let mut sigma = vec![0.0; problem.nodes()];
        let stop = Stop { steps: 50, tolerance: 1e-4 };
        let steps = CpuFista::new(&problem).solve(&problem, &mut sigma, stop, &|_| false, &mut |_, _| {}).unwrap();
        assert_eq!(steps, 3);
        assert!(sigma.iter().all(|&s| s == 0.0));
    }
}
