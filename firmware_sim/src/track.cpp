#include "fsim/track.hpp"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <limits>
#include <sstream>
#include <stdexcept>

namespace fsim {
namespace {

double wrap_mod(double s, double length) {
  double r = std::fmod(s, length);
  return r < 0.0 ? r + length : r;
}

std::vector<Vec2> drop_closing_and_repeats(std::vector<Vec2> p) {
  double scale = 1.0;
  if (!p.empty()) {
    Eigen::Vector2d lo = p[0], hi = p[0];
    for (const auto& q : p) {
      lo = lo.cwiseMin(q);
      hi = hi.cwiseMax(q);
    }
    scale = std::max(1.0, (hi - lo).maxCoeff());
  }
  while (p.size() > 3 && (p.back() - p.front()).norm() <= 1e-9 * scale) p.pop_back();
  std::vector<Vec2> out;
  out.reserve(p.size());
  for (size_t i = 0; i < p.size(); ++i) {
    const Vec2& next = p[(i + 1) % p.size()];
    if ((next - p[i]).norm() > 1e-12 * scale) out.push_back(p[i]);
  }
  return out;
}

// two comma-separated rows: x values, then y values
std::vector<Vec2> read_rows_xy(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error("track file not found: " + path);
  std::vector<std::vector<double>> rows;
  std::string line;
  while (std::getline(in, line)) {
    if (line.find_first_not_of(" \t\r") == std::string::npos) continue;
    std::vector<double> row;
    std::stringstream ss(line);
    std::string cell;
    while (std::getline(ss, cell, ',')) {
      try {
        row.push_back(std::stod(cell));
      } catch (const std::exception&) {
        throw std::runtime_error(path + ": not a number: '" + cell + "'");
      }
    }
    rows.push_back(std::move(row));
  }
  if (rows.size() != 2 || rows[0].size() != rows[1].size() || rows[0].size() < 4)
    throw std::runtime_error(path + ": expected two rows (x then y) of equal length >= 4");
  std::vector<Vec2> p(rows[0].size());
  for (size_t i = 0; i < p.size(); ++i) {
    p[i] = Vec2(rows[0][i], rows[1][i]);
    if (!p[i].allFinite()) throw std::runtime_error(path + ": non-finite point");
  }
  return p;
}

}  // namespace

Polyline::Polyline(std::vector<Vec2> points) : p_(drop_closing_and_repeats(std::move(points))) {
  if (p_.size() < 3) throw std::runtime_error("a closed polyline needs at least 3 distinct points");
  const size_t n = p_.size();
  d_.resize(n);
  len_.resize(n);
  s_.resize(n);
  double s = 0.0;
  for (size_t i = 0; i < n; ++i) {
    d_[i] = p_[(i + 1) % n] - p_[i];
    len_[i] = d_[i].norm();
    s_[i] = s;
    s += len_[i];
  }
  length_ = s;
}

Polyline::Nearest Polyline::nearest(const Vec2& q, int first, int count) const {
  const int n = size();
  if (count <= 0 || count > n) {
    first = 0;
    count = n;
  }
  Nearest best;
  best.dist2 = std::numeric_limits<double>::infinity();
  for (int k = 0; k < count; ++k) {
    const int i = ((first + k) % n + n) % n;
    const double l2 = len_[i] * len_[i];
    const Vec2 r = q - p_[i];
    const double t = l2 > 0.0 ? std::clamp(r.dot(d_[i]) / l2, 0.0, 1.0) : 0.0;
    const double e2 = (r - t * d_[i]).squaredNorm();
    if (e2 < best.dist2) best = Nearest{i, t, e2};
  }
  return best;
}

double Polyline::signed_area() const {
  double a = 0.0;
  for (int i = 0; i < size(); ++i) {
    const Vec2& p = p_[i];
    const Vec2& q = p_[(i + 1) % size()];
    a += p.x() * q.y() - q.x() * p.y();
  }
  return 0.5 * a;
}

Track::Track(std::string name, std::vector<Vec2> center, std::vector<Vec2> bound_a, std::vector<Vec2> bound_b)
    : name_(std::move(name)), center_(std::move(center)) {
  Polyline a(std::move(bound_a)), b(std::move(bound_b));
  // the bound whose points lie mostly to the left of the centre line is the left one
  std::vector<double> lat;
  for (const auto& q : a.points()) lat.push_back(project(q).lateral);
  std::nth_element(lat.begin(), lat.begin() + lat.size() / 2, lat.end());
  const bool a_left = lat[lat.size() / 2] > 0.0;
  left_ = a_left ? a : b;
  right_ = a_left ? b : a;
  std::vector<double> total;
  for (const auto& q : center_.points()) {
    half_left_.push_back(left_.distance(q));
    half_right_.push_back(right_.distance(q));
    total.push_back(half_left_.back() + half_right_.back());
  }
  std::nth_element(total.begin(), total.begin() + total.size() / 2, total.end());
  width_ = total[total.size() / 2];
}

Track Track::load(const std::string& dir, const std::string& name) {
  const std::string base = dir + "/" + name;
  return Track(name, read_rows_xy(base + "_center.txt"), read_rows_xy(base + "_inner.txt"),
               read_rows_xy(base + "_outer.txt"));
}

double Track::interpolate(const std::vector<double>& values, double s) const {
  if (values.empty()) return 0.0;
  s = wrap_mod(s, length());
  const int n = center_.size();
  // segments are few hundred: binary search over the start arc lengths
  int lo = 0, hi = n - 1;
  while (lo < hi) {
    const int mid = (lo + hi + 1) / 2;
    if (center_.arc_start(mid) <= s) lo = mid; else hi = mid - 1;
  }
  const double t = (s - center_.arc_start(lo)) / center_.segment_length(lo);
  return values[lo] * (1.0 - t) + values[(lo + 1) % n] * t;
}

Projection Track::finish(const Vec2& q, const Polyline::Nearest& n) const {
  Projection p;
  const int i = n.segment;
  p.s = wrap_mod(center_.arc_start(i) + n.t * center_.segment_length(i), length());
  const Vec2 d = center_.direction(i);
  const Vec2 r = q - center_.points()[i];
  const double cross = d.x() * r.y() - d.y() * r.x();
  p.lateral = (cross >= 0.0 ? 1.0 : -1.0) * std::sqrt(n.dist2);
  p.half_width_left = interpolate(half_left_, p.s);
  p.half_width_right = interpolate(half_right_, p.s);
  return p;
}

Projection Track::project(const Vec2& q) const { return finish(q, center_.nearest(q)); }

Projection Track::project(const Vec2& q, double s_hint, double window) const {
  const int n = center_.size();
  const double mean_len = length() / n;
  const int w = std::min(n / 2, static_cast<int>(std::ceil(window / mean_len)) + 1);
  // segment containing s_hint
  const double s = wrap_mod(s_hint, length());
  int lo = 0, hi = n - 1;
  while (lo < hi) {
    const int mid = (lo + hi + 1) / 2;
    if (center_.arc_start(mid) <= s) lo = mid; else hi = mid - 1;
  }
  return finish(q, center_.nearest(q, lo - w, 2 * w + 1));
}

Vec2 Track::position(double s) const {
  s = wrap_mod(s, length());
  const int n = center_.size();
  int lo = 0, hi = n - 1;
  while (lo < hi) {
    const int mid = (lo + hi + 1) / 2;
    if (center_.arc_start(mid) <= s) lo = mid; else hi = mid - 1;
  }
  const double t = (s - center_.arc_start(lo)) / center_.segment_length(lo);
  return center_.points()[lo] + t * center_.direction(lo);
}

double Track::heading_at(double s) const {
  const Vec2 a = position(s), b = position(s + 1e-3);
  return std::atan2(b.y() - a.y(), b.x() - a.x());
}

std::array<Vec2, 4> Footprint::corners(double x, double y, double yaw) const {
  const Vec2 fwd(std::cos(yaw), std::sin(yaw));
  const Vec2 left(-fwd.y(), fwd.x());
  // the rectangle's centre sits half-way between the axles
  const Vec2 c = Vec2(x, y) + 0.5 * (lf - lr) * fwd;
  const Vec2 hl = 0.5 * length * fwd, hw = 0.5 * width * left;
  return {c + hl + hw, c + hl - hw, c - hl - hw, c - hl + hw};
}

double footprint_clearance(const Track& track, const Footprint& fp, double x, double y, double yaw,
                           double s_hint, double window) {
  double worst = std::numeric_limits<double>::infinity();
  for (const auto& corner : fp.corners(x, y, yaw))
    worst = std::min(worst, track.project(corner, s_hint, window).boundary_distance());
  return worst;
}

}  // namespace fsim
