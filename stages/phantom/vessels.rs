//! Pulmonary vessel trees. Owns their growth, by space colonisation (Runions et al. 2007):
//! attraction points scattered uniformly through a lung pull the tree out from its root in
//! small steps; a point dies once a branch reaches it, so the tree fills the whole lung
//! evenly, branching wherever two groups of points pull apart. Radii then follow Murray's
//! law from the twigs inward (r³ of a vessel = Σ r³ of its branches), so vessels taper from
//! ~10–12 mm at the hilum to the minimum radius at the periphery.
//!
//! Growth is sequential in one seeded stream: the same seed gives the same tree.

use super::frame::Aabb;
use super::shapes::V3;
use super::tubes::Capsule;
use glam::Vec3;
use rand::Rng;
use rand_chacha::ChaCha8Rng;

/// Where a tree enters its lung and how finely it branches (reference frame, mm).
#[derive(Debug, Clone)]
pub(crate) struct TreeSpec {
    /// Where the tree's trunk leaves the mediastinum (hilum or atrium).
    pub hilum: V3,
    /// Direction the trunk runs from there until it is inside the lung.
    pub trunk_dir: V3,
    /// Box the lung lies in (attraction points are drawn in it, inside the lung).
    pub lung_box: Aabb,
    /// Number of attraction points: about the number of twigs.
    pub points: usize,
    /// Radius of the twigs.
    pub min_radius_mm: f32,
}

/// Length of one growth step.
const STEP_MM: f32 = 3.0;
/// A point pulls on its nearest node if that node is closer than this.
const INFLUENCE_MM: f32 = 30.0;
/// A point is reached (and removed) once a node comes this close.
const KILL_MM: f32 = 6.0;
/// Attraction points stay this far inside the pleura.
const POINT_MARGIN_MM: f32 = 3.0;
const MAX_ITERATIONS: usize = 400;

struct Node {
    pos: V3,
    parent: Option<usize>,
}

/// Grow one tree inside the lung whose signed distance is `lung_sd` (mm, negative inside).
/// Returns its segments, reference frame.
pub(crate) fn grow_tree(spec: &TreeSpec, lung_sd: &dyn Fn(V3) -> f32, rng: &mut ChaCha8Rng) -> Vec<Capsule> {
    let points = attraction_points(spec, lung_sd, rng);
    let root = trunk_end(spec, lung_sd);
    let mut nodes = vec![Node { pos: root, parent: None }];
    let mut colony = Colony::new(points, &spec.lung_box);
    colony.node_added(0, root);
    for _ in 0..MAX_ITERATIONS {
        let pulls = colony.pulls(&nodes);
        let before = nodes.len();
        for (n, pull) in pulls.into_iter().enumerate() {
            let Some(sum) = pull else { continue };
            // A tiny random tilt breaks the tie of points pulling in opposite directions.
            let jitter: V3 = std::array::from_fn(|_| rng.gen_range(-0.05..0.05));
            let dir = (Vec3::from(sum).normalize_or(Vec3::Z) + Vec3::from(jitter)).normalize_or(Vec3::Z);
            let pos = (Vec3::from(nodes[n].pos) + dir * STEP_MM).to_array();
            if lung_sd(pos) < -0.5 {
                nodes.push(Node { pos, parent: Some(n) });
            }
        }
        if nodes.len() == before {
            break;
        }
        for (n, node) in nodes.iter().enumerate().skip(before) {
            colony.node_added(n, node.pos);
        }
        if colony.alive == 0 {
            break;
        }
    }
    let (mut segments, root_radius) = murray_segments(&nodes, spec.min_radius_mm);
    segments.push(Capsule { a: spec.hilum, b: root, radius_a_mm: root_radius, radius_b_mm: root_radius });
    segments
}

/// Points drawn uniformly in the lung, `POINT_MARGIN_MM` inside it.
fn attraction_points(spec: &TreeSpec, lung_sd: &dyn Fn(V3) -> f32, rng: &mut ChaCha8Rng) -> Vec<V3> {
    let b = &spec.lung_box;
    let mut points = Vec::with_capacity(spec.points);
    // Rejection sampling; the guard bounds the work if the box barely holds lung.
    for _ in 0..spec.points * 200 {
        if points.len() == spec.points {
            break;
        }
        let p: V3 = std::array::from_fn(|a| rng.gen_range(b.min[a]..b.max[a]) as f32);
        if lung_sd(p) < -POINT_MARGIN_MM {
            points.push(p);
        }
    }
    points
}

/// Where the trunk, run from the hilum along its direction, is first well inside the lung.
fn trunk_end(spec: &TreeSpec, lung_sd: &dyn Fn(V3) -> f32) -> V3 {
    let dir = Vec3::from(spec.trunk_dir).normalize_or(Vec3::Z);
    let mut p = spec.hilum;
    for _ in 0..120 {
        if lung_sd(p) < -4.0 {
            break;
        }
        p = (Vec3::from(p) + dir).to_array();
    }
    p
}

/// Radii by Murray's law from the twigs inward, then one capsule per node joining it to
/// its parent, with the node's radius. Also returns the root's radius.
fn murray_segments(nodes: &[Node], min_radius_mm: f32) -> (Vec<Capsule>, f32) {
    // Children are created after their parents: accumulate r³ from the last node back.
    let mut cubes = vec![0.0f32; nodes.len()];
    for n in (0..nodes.len()).rev() {
        let own = cubes[n].max(min_radius_mm.powi(3));
        cubes[n] = own;
        if let Some(p) = nodes[n].parent {
            cubes[p] += own;
        }
    }
    let radius = |n: usize| cubes[n].cbrt();
    let segments = nodes
        .iter()
        .enumerate()
        .filter_map(|(n, node)| {
            node.parent.map(|p| Capsule {
                a: nodes[p].pos,
                b: node.pos,
                radius_a_mm: radius(n),
                radius_b_mm: radius(n),
            })
        })
        .collect();
    (segments, radius(0))
}

/// The attraction points, each with its nearest node, in a grid for fast neighbourhood
/// updates when nodes are added.
struct Colony {
    points: Vec<V3>,
    nearest: Vec<Option<(usize, f32)>>,
    dead: Vec<bool>,
    alive: usize,
    grid: Grid,
}

impl Colony {
    fn new(points: Vec<V3>, lung_box: &Aabb) -> Colony {
        let grid = Grid::new(&points, lung_box, INFLUENCE_MM);
        let n = points.len();
        Colony { points, nearest: vec![None; n], dead: vec![false; n], alive: n, grid }
    }

    /// A node appeared at `pos`: points near it may now pull on it, or be reached.
    fn node_added(&mut self, node: usize, pos: V3) {
        for q in self.grid.near(pos) {
            if self.dead[q] {
                continue;
            }
            let d = (Vec3::from(self.points[q]) - Vec3::from(pos)).length();
            if d < KILL_MM {
                self.dead[q] = true;
                self.alive -= 1;
            } else if d < INFLUENCE_MM && self.nearest[q].is_none_or(|(_, best)| d < best) {
                self.nearest[q] = Some((node, d));
            }
        }
    }

    /// For each node, the sum of unit vectors toward the live points it is nearest to.
    fn pulls(&self, nodes: &[Node]) -> Vec<Option<V3>> {
        let mut pulls: Vec<Option<V3>> = vec![None; nodes.len()];
        for (q, p) in self.points.iter().enumerate() {
            if self.dead[q] {
                continue;
            }
            if let Some((n, _)) = self.nearest[q] {
                let unit = (Vec3::from(*p) - Vec3::from(nodes[n].pos)).normalize_or(Vec3::Z);
                let sum = pulls[n].get_or_insert([0.0; 3]);
                *sum = (Vec3::from(*sum) + unit).to_array();
            }
        }
        pulls
    }
}

/// Uniform grid of point indices with cells as large as the influence radius.
struct Grid {
    lo: V3,
    cell_mm: f32,
    dims: [usize; 3],
    cells: Vec<Vec<usize>>,
}

impl Grid {
    fn new(points: &[V3], b: &Aabb, cell_mm: f32) -> Grid {
        let lo = b.min.map(|v| v as f32);
        let dims: [usize; 3] =
            std::array::from_fn(|a| (((b.max[a] - b.min[a]) as f32 / cell_mm).ceil() as usize).max(1));
        let mut cells = vec![Vec::new(); dims.iter().product()];
        let mut grid = Grid { lo, cell_mm, dims, cells: Vec::new() };
        for (q, p) in points.iter().enumerate() {
            let c = grid.cell_of(*p);
            cells[grid.flat(c)].push(q);
        }
        grid.cells = cells;
        grid
    }

    fn cell_of(&self, p: V3) -> [usize; 3] {
        std::array::from_fn(|a| (((p[a] - self.lo[a]) / self.cell_mm).floor().max(0.0) as usize).min(self.dims[a] - 1))
    }

    fn flat(&self, c: [usize; 3]) -> usize {
        c[0] + self.dims[0] * (c[1] + self.dims[1] * c[2])
    }

    /// Indices of the points in the 27 cells around `p`.
    fn near(&self, p: V3) -> Vec<usize> {
        let c = self.cell_of(p);
        let range = |a: usize| c[a].saturating_sub(1)..=(c[a] + 1).min(self.dims[a] - 1);
        let mut out = Vec::new();
        for k in range(2) {
            for j in range(1) {
                for i in range(0) {
                    out.extend_from_slice(&self.cells[self.flat([i, j, k])]);
                }
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn ball_spec() -> TreeSpec {
        TreeSpec {
            hilum: [-70.0, 0.0, 0.0],
            trunk_dir: [1.0, 0.0, 0.0],
            lung_box: Aabb::new([-60.0; 3], [60.0; 3]),
            points: 600,
            min_radius_mm: 0.4,
        }
    }

    #[test]
    fn tree_fills_its_lung_and_tapers_by_murray() {
        // A 120-mm ball as the lung, the hilum outside it.
        let lung = |p: V3| Vec3::from(p).length() - 60.0;
        let spec = ball_spec();
        let tree = grow_tree(&spec, &lung, &mut ChaCha8Rng::seed_from_u64(3));
        assert!(tree.len() > 500, "{} segments", tree.len());
        let trunk = tree.last().unwrap();
        // 600 twigs of 0.4 mm: a root of about 0.4·600^(1/3) ≈ 3.4 mm.
        assert!((2.5..4.5).contains(&trunk.radius_a_mm), "{trunk:?}");
        for c in &tree[..tree.len() - 1] {
            assert!(lung(c.b) < -0.4, "{c:?} leaves the lung");
            assert!(c.radius_b_mm >= 0.4 - 1e-6);
        }
        // Branches reach every octant of the ball.
        for octant in 0..8 {
            let sign = |a: usize| if octant >> a & 1 == 0 { -1.0 } else { 1.0 };
            let reached = tree.iter().any(|c| (0..3).all(|a| c.b[a] * sign(a) > 15.0));
            assert!(reached, "octant {octant} empty");
        }
        let again = grow_tree(&spec, &lung, &mut ChaCha8Rng::seed_from_u64(3));
        assert_eq!(tree, again);
    }
}
