// fsim/track.hpp - a closed race track for the SIL plant: centre line, bounds, projection,
// and the car's footprint against the bounds.
//
// Same conventions as train/model/tracks.py (the Python reference): the centre line is a closed
// polyline without a repeated end point; arc length s in [0, length); lateral offset positive
// to the left of the direction of travel; which bound file is the left one is worked out from
// the data. Files: <dir>/<name>_center.txt, _inner.txt, _outer.txt, two comma-separated rows
// (x, then y, metres).
#pragma once

#include <Eigen/Core>
#include <array>
#include <string>
#include <vector>

namespace fsim {

using Vec2 = Eigen::Vector2d;

// A closed polyline given as points without a repeated end point.
class Polyline {
 public:
  Polyline() = default;
  explicit Polyline(std::vector<Vec2> points);
  // nearest point: segment index, parameter t in [0, 1], squared distance. Searches segments
  // [first, first + count) modulo n (count <= 0: all).
  struct Nearest {
    int segment = 0;
    double t = 0.0;
    double dist2 = 0.0;
  };
  Nearest nearest(const Vec2& q, int first = 0, int count = 0) const;
  double distance(const Vec2& q) const { return std::sqrt(nearest(q).dist2); }
  const std::vector<Vec2>& points() const { return p_; }
  int size() const { return static_cast<int>(p_.size()); }
  double length() const { return length_; }
  double arc_start(int segment) const { return s_[segment]; }
  double segment_length(int segment) const { return len_[segment]; }
  Vec2 direction(int segment) const { return d_[segment]; }
  double signed_area() const;

 private:
  std::vector<Vec2> p_, d_;
  std::vector<double> len_, s_;
  double length_ = 0.0;
};

struct Projection {
  double s = 0.0;        // arc length of the nearest centre-line point
  double lateral = 0.0;  // signed, + to the left
  double half_width_left = 0.0;
  double half_width_right = 0.0;
  // lateral distance to the nearer bound: + inside, - outside
  double boundary_distance() const {
    return std::min(half_width_left - lateral, half_width_right + lateral);
  }
};

class Track {
 public:
  Track(std::string name, std::vector<Vec2> center, std::vector<Vec2> bound_a, std::vector<Vec2> bound_b);
  // Read <dir>/<name>_center.txt, _inner.txt, _outer.txt; throws std::runtime_error naming the file.
  static Track load(const std::string& dir, const std::string& name);

  const std::string& name() const { return name_; }
  double length() const { return center_.length(); }
  double width() const { return width_; }
  const Polyline& center() const { return center_; }
  const Polyline& left_bound() const { return left_; }
  const Polyline& right_bound() const { return right_; }

  // Project onto the centre line. With a hint (s of the previous call), only segments within
  // +-window metres are searched: fast, and no jump onto a neighbouring part of the track.
  Projection project(const Vec2& q) const;
  Projection project(const Vec2& q, double s_hint, double window) const;
  Vec2 position(double s) const;
  double heading_at(double s) const;
  // a value given per centre-line point (as many as the centre line has), linear between them, at s
  double interpolate(const std::vector<double>& values, double s) const;

 private:
  Projection finish(const Vec2& q, const Polyline::Nearest& n) const;

  std::string name_;
  Polyline center_, left_, right_;
  std::vector<double> half_left_, half_right_;  // at the centre points
  double width_ = 0.0;
};

// The car's rectangular footprint: length x width, centred half-way between the axles
// (reference point = centre of gravity, lf ahead to the front axle, lr behind to the rear).
struct Footprint {
  double length = 0.0;
  double width = 0.0;
  double lf = 0.0;
  double lr = 0.0;
  // corners in the world frame: front-left, front-right, rear-right, rear-left
  std::array<Vec2, 4> corners(double x, double y, double yaw) const;
};

// The car's worst corner against the bounds: the smallest boundary distance of the four corners
// (negative: that corner is outside by that much).
double footprint_clearance(const Track& track, const Footprint& fp, double x, double y, double yaw,
                           double s_hint, double window);

}  // namespace fsim
