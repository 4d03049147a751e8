// How a production rig's targets drive its sculpted shapes: in-betweens, combinations and masks (the rig
// file's semantics). A frame's target weights become one weight per sculpted shape (Rig::ShapeWeights), and
// everything that blends per shape (positions, rest lengths, the anchor's motion, the target paths) blends
// with those. At an in-between's weight, or a combination's drivers at 1, exactly one shape has weight 1 and
// every other 0, so that shape is reproduced exactly.
#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <deque>
#include <map>

#include "anchor.h"
#include "rig_builder.h"
#include "springblend/error.h"
#include "springblend/solve.h"

namespace springblend {

namespace {

[[noreturn]] void Fail(const std::string& target, const std::string& what) {
  throw Error(ErrorCode::kInvalidInput, fmt::format("target '{}': {}", target, what));
}

}  // namespace

void ValidateInbetweenWeights(const std::vector<double>& weights, const std::function<std::string(size_t)>& field) {
  const auto fail = [](const std::string& what) { throw Error(ErrorCode::kInvalidInput, what); };
  for (size_t i = 0; i < weights.size(); ++i) {
    const double w = weights[i];
    if (!(w > 0.0 && w < 1.0)) fail(fmt::format("{} = {} is outside (0, 1)", field(i), w));
    if (w < kMinInbetweenSpacing || w > 1.0 - kMinInbetweenSpacing) {
      fail(fmt::format("{} = {} is within {:g} of {}: in-between weights must be in [{:g}, 1 - {:g}]", field(i), w,
                       kMinInbetweenSpacing, w < 0.5 ? 0 : 1, kMinInbetweenSpacing, kMinInbetweenSpacing));
    }
    for (size_t j = 0; j < i; ++j) {
      if (w == weights[j]) fail(fmt::format("{} = {} is repeated", field(i), w));
      if (std::abs(w - weights[j]) < kMinInbetweenSpacing) {
        fail(fmt::format("{} = {} is within {:g} of {} = {}: in-betweens must be at least {:g} apart", field(i), w,
                         kMinInbetweenSpacing, field(j), weights[j], kMinInbetweenSpacing));
      }
    }
  }
}

void RigBuilder::ExpandSpecs(std::vector<TargetSpec> specs) {
  Rig& rig = r_;
  internal::ShapeControls& controls = rig.internals_->controls;
  if (specs.empty()) {
    throw Error(ErrorCode::kInvalidInput,
                "a rig needs at least one target besides the rest shape " + rig.rest_.source);
  }
  const Eigen::Index n = rig.rest_.vertices.rows();
  std::map<std::string, int> index;  // name -> target (ordinary) or -1 (combination)
  for (size_t i = 0; i < specs.size(); ++i) {
    const TargetSpec& spec = specs[i];
    if (spec.name.empty()) {
      throw Error(ErrorCode::kInvalidInput, fmt::format("targets[{}] ({}): name is empty", i, spec.mesh.source));
    }
    if (index.count(spec.name) > 0) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("{}: target '{}': name is used twice; target names must be unique", spec.mesh.source,
                              spec.name));
    }
    index[spec.name] = spec.combination.empty() ? static_cast<int>(rig.target_names_.size()) : -1;
    if (spec.combination.empty()) rig.target_names_.push_back(spec.name);
  }
  // How far a shape may take a vertex from the rest shape (its mask included): a target farther off than
  // kMaxTargetReach diagonals is an export or unit error, and would cost its path minutes of solving.
  const double diagonal = BoundingBoxDiagonal(rig.rest_.vertices);
  const auto check_reach = [&](const TargetSpec& spec, const TriangleMesh& mesh, const std::string& what) {
    if (mesh.vertices.rows() != n || !(diagonal > 0.0)) return;  // the topology check names those
    for (Eigen::Index v = 0; v < n; ++v) {
      const double scale = spec.mask.empty() || static_cast<Eigen::Index>(spec.mask.size()) != n
                               ? 1.0
                               : std::abs(spec.mask[static_cast<size_t>(v)]);
      const double reach = scale * (mesh.vertices.row(v) - rig.rest_.vertices.row(v)).norm();
      if (std::isfinite(reach) && reach > kMaxTargetReach * diagonal) {  // the mesh checks name non-finite ones
        Fail(spec.name, fmt::format("{}vertex {} moves {:.6g} from the rest shape{}, more than {:g} times the rest "
                                    "mesh's bounding-box diagonal ({:.6g}): a target this far off is an export or "
                                    "unit error",
                                    what, v, reach, scale != 1.0 ? fmt::format(" (with its mask {:g})", scale) : "",
                                    kMaxTargetReach, diagonal));
      }
    }
  };
  // Shapes: the targets at 1 (shape t = target t), then their in-betweens, then the combinations.
  std::vector<TriangleMesh> shapes;
  std::vector<std::vector<double>> masks;
  controls.targets.assign(rig.target_names_.size(), {});
  for (TargetSpec& spec : specs) {
    if (!spec.mask.empty()) {
      if (!spec.combination.empty()) {
        Fail(spec.name, "mask: a combination takes no mask (mask its drivers instead)");
      }
      if (static_cast<Eigen::Index>(spec.mask.size()) != n) {
        Fail(spec.name, fmt::format("mask has {} values but the rest shape {} has {} vertices", spec.mask.size(),
                                    rig.rest_.source, n));
      }
      for (size_t v = 0; v < spec.mask.size(); ++v) {
        if (!std::isfinite(spec.mask[v])) Fail(spec.name, fmt::format("mask[{}] is not finite", v));
        if (std::abs(spec.mask[v]) > kMaxTargetWeight) {
          Fail(spec.name, fmt::format("mask[{}] = {} is beyond +-{:g}: the blended shape would overflow", v,
                                      spec.mask[v], kMaxTargetWeight));
        }
      }
    }
    check_reach(spec, spec.mesh, "");
    for (size_t i = 0; i < spec.inbetweens.size(); ++i) {
      check_reach(spec, spec.inbetweens[i].mesh, fmt::format("inbetweens[{}]: ", i));
    }
    if (!spec.combination.empty()) continue;
    const int t = index[spec.name];
    spec.mesh.name = spec.name;
    controls.targets[t].push_back({1.0, t});
    shapes.push_back(std::move(spec.mesh));
    masks.push_back(spec.mask);
  }
  for (TargetSpec& spec : specs) {
    if (!spec.combination.empty()) {
      if (!spec.inbetweens.empty()) {
        Fail(spec.name, "inbetweens: a combination takes no in-betweens");
      }
      continue;
    }
    const int t = index[spec.name];
    std::vector<double> weights;
    for (const Inbetween& inbetween : spec.inbetweens) weights.push_back(inbetween.weight);
    try {
      ValidateInbetweenWeights(weights, [](size_t i) { return fmt::format("inbetweens[{}].weight", i); });
    } catch (const Error& e) {
      Fail(spec.name, e.what());
    }
    std::sort(spec.inbetweens.begin(), spec.inbetweens.end(),
              [](const Inbetween& a, const Inbetween& b) { return a.weight < b.weight; });
    std::vector<internal::ShapeControls::Knot> knots;
    for (Inbetween& inbetween : spec.inbetweens) {
      knots.push_back({inbetween.weight, static_cast<int>(shapes.size())});
      inbetween.mesh.name = fmt::format("{}@{}", spec.name, inbetween.weight);
      shapes.push_back(std::move(inbetween.mesh));
      masks.push_back(spec.mask);  // a target's mask holds on its way there too
    }
    knots.push_back(controls.targets[t].back());
    controls.targets[t] = std::move(knots);
  }
  for (TargetSpec& spec : specs) {
    if (spec.combination.empty()) continue;
    if (spec.combination.size() < 2) {
      Fail(spec.name, fmt::format("combination names {} target; a combination needs at least two drivers",
                                  spec.combination.size()));
    }
    internal::ShapeControls::Combination combination;
    for (size_t i = 0; i < spec.combination.size(); ++i) {
      const std::string& driver = spec.combination[i];
      const auto it = index.find(driver);
      if (it == index.end()) {
        Fail(spec.name, fmt::format("combination[{}] = '{}' is not a target of this rig", i, driver));
      }
      if (it->second < 0) {
        Fail(spec.name, fmt::format("combination[{}] = '{}' is a combination; drivers must be ordinary targets", i,
                                    driver));
      }
      if (std::find(combination.drivers.begin(), combination.drivers.end(), it->second) !=
          combination.drivers.end()) {
        Fail(spec.name, fmt::format("combination[{}] = '{}' is named twice", i, driver));
      }
      combination.drivers.push_back(it->second);
    }
    combination.shape = static_cast<int>(shapes.size());
    spec.mesh.name = spec.name;
    shapes.push_back(std::move(spec.mesh));
    masks.emplace_back();
    controls.combinations.push_back(std::move(combination));
    rig.combination_names_.push_back(spec.name);
  }
  rig.targets_ = std::move(shapes);
  const bool any_mask = std::any_of(masks.begin(), masks.end(), [](const auto& m) { return !m.empty(); });
  if (any_mask) controls.masks = std::move(masks);
}

void RigBuilder::ApplyMasks() {
  Rig& rig = r_;
  const internal::ShapeControls& controls = rig.internals_->controls;
  if (controls.masks.empty()) return;
  const int surface = rig.summary_.surface_vertices;
  const int n = rig.summary_.vertices;
  // Each vertex off the surface takes the value of the surface vertex nearest along the springs (breadth
  // first from every surface vertex at once; ties go to the lower index, deterministically).
  std::vector<int> source(n, -1);
  std::deque<int> queue;
  for (int v = 0; v < surface; ++v) {
    source[v] = v;
    queue.push_back(v);
  }
  while (!queue.empty()) {
    const int v = queue.front();
    queue.pop_front();
    for (int k = rig.vertex_spring_offsets_[v]; k < rig.vertex_spring_offsets_[v + 1]; ++k) {
      const int q = rig.vertex_springs_[k];
      const int u = rig.spring_a_[q] == v ? rig.spring_b_[q] : rig.spring_a_[q];
      if (source[u] < 0) {
        source[u] = source[v];
        queue.push_back(u);
      }
    }
  }
  const Points& rest = rig.shapes_[0];
  Points anchor_rest(static_cast<Eigen::Index>(rig.anchor_.size()), 3), anchor_moved = anchor_rest;
  for (size_t i = 0; i < rig.anchor_.size(); ++i) {
    anchor_rest.row(static_cast<Eigen::Index>(i)) = rest.row(rig.anchor_[i]);
  }
  for (size_t s = 0; s < controls.masks.size(); ++s) {
    const std::vector<double>& mask = controls.masks[s];
    if (mask.empty()) continue;
    const auto value = [&](int v) { return source[v] >= 0 ? mask[source[v]] : 0.0; };
    Points& shape = rig.shapes_[s + 1];
    for (int v = 0; v < n; ++v) shape.row(v) = rest.row(v) + value(v) * (shape.row(v) - rest.row(v));
    rig.targets_[s].vertices = shape.topRows(surface);
    std::vector<double>& delta = rig.rest_length_delta_[s];
    bool changes = false;
    for (size_t q = 0; q < delta.size(); ++q) {
      delta[q] *= 0.5 * (value(rig.spring_a_[q]) + value(rig.spring_b_[q]));
      changes = changes || delta[q] != 0.0;
    }
    rig.target_changes_lengths_[s] = changes ? 1 : 0;
    if (!rig.anchor_.empty() && s < rig.internals_->anchor_motions.size()) {
      for (size_t i = 0; i < rig.anchor_.size(); ++i) {
        anchor_moved.row(static_cast<Eigen::Index>(i)) = shape.row(rig.anchor_[i]);
      }
      rig.internals_->anchor_motions[s] = internal::FitRigidMotion(anchor_rest, anchor_moved);
    }
  }
}

std::vector<double> Rig::ShapeWeights(const std::vector<double>& weights) const {
  const internal::ShapeControls& controls = internals_->controls;
  std::vector<double> omega(targets_.size(), 0.0);
  for (size_t t = 0; t < controls.targets.size() && t < weights.size(); ++t) {
    const auto& knots = controls.targets[t];
    const double w = weights[t];
    if (w == 0.0) continue;
    // The segment [a, b] of the piecewise-linear path holding w (the first or last one extrapolated); the
    // knot at 0 is the rest shape, which has no weight of its own.
    size_t i = 0;  // b = knots[i]
    while (i + 1 < knots.size() && w > knots[i].weight) ++i;
    const double a = i == 0 ? 0.0 : knots[i - 1].weight;
    const double b = knots[i].weight;
    const double u = (w - a) / (b - a);
    omega[knots[i].shape] += u;
    if (i > 0) omega[knots[i - 1].shape] += 1.0 - u;
  }
  for (const auto& combination : controls.combinations) {
    double product = 1.0;
    for (int d : combination.drivers) product *= d < static_cast<int>(weights.size()) ? weights[d] : 0.0;
    if (product == 0.0) continue;
    omega[combination.shape] += product;
    for (int d : combination.drivers) omega[controls.targets[d].back().shape] -= product;
  }
  return omega;
}

}  // namespace springblend
