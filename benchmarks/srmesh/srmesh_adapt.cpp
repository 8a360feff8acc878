// Per-frame adapt of Hoppe's selectively refinable mesh (SrMesh, from the
// Mesh-processing-library) along a camera path, timed frame by frame.
//
// Usage:
//   srmesh_adapt MESH.pm|MESH.srm CAMERAS.txt TAU [--passes N]   print a table
//   srmesh_adapt MESH.pm|MESH.srm CAMERAS.txt TAU --serve        answer "pass" lines on stdin
//
// MESH is an SR progressive mesh (MeshSimplify -vsgeom, then Filterprog -pm)
// or its .srm form. CAMERAS.txt has one camera per line after '#' comments:
//   eye_x eye_y eye_z  look_x look_y look_z  up_x up_y up_z  fov_y_deg near far width height
// (benchmarks/srmesh/cameras.py writes it from pmjax cameras). TAU is the
// screen-space tolerance in pixels of the image height, as in pmjax.
//
// A pass: the mesh fully coarsened (not timed), then for each camera in turn
// one set_view_params + one adapt_refinement (timed), the active mesh kept
// as SrMesh keeps it for drawing (its active vertex and face lists). Geomorphs
// are off (refine and coarsen morph times 0), as pmjax has none.
//
// Output of a pass: a line "ms t0 t1 ..." (wall milliseconds per frame), a
// line "faces n0 n1 ..." (active faces after each frame's adapt) and a line
// "cpu_ms c" (the thread's CPU milliseconds over the pass's frames: on a
// shared machine, the wall times less the time the thread was preempted).

#include <time.h>

#include <chrono>
#include <cmath>
#include <fstream>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

#include "libHh/Geometry.h"
#include "libHh/PMesh.h"
#include "libHh/SrMesh.h"

using namespace hh;

namespace {

struct Camera {
  float eye[3], look[3], up[3];
  float fov_y_deg, near, far;
  int width, height;
};

std::vector<Camera> read_cameras(const std::string& path) {
  std::ifstream is(path);
  if (!is) throw std::runtime_error("cannot open camera file " + path);
  std::vector<Camera> cams;
  for (std::string line; std::getline(is, line);) {
    if (line.empty() || line[0] == '#') continue;
    std::istringstream ls(line);
    Camera c;
    for (float& x : c.eye) ls >> x;
    for (float& x : c.look) ls >> x;
    for (float& x : c.up) ls >> x;
    ls >> c.fov_y_deg >> c.near >> c.far >> c.width >> c.height;
    if (!ls) throw std::runtime_error("bad camera line in " + path + ": " + line);
    cams.push_back(c);
  }
  if (cams.empty()) throw std::runtime_error("no cameras in " + path);
  return cams;
}

// Read an SR progressive mesh (*.pm, first non-comment byte 'P') or its
// *.srm form ('S'), as G3dOGL's -sr_mode viewer reads it.
void read_srmesh(SrMesh& srmesh, const std::string& path) {
  std::ifstream is(path, std::ios::binary);
  if (!is) throw std::runtime_error("cannot open mesh " + path);
  for (std::string line; is.peek() == '#';) std::getline(is, line);
  if (is.peek() == 'S') {
    srmesh.read_srm(is);
  } else if (is.peek() == 'P') {
    PMeshRStream pmrs(is);
    srmesh.read_pm(pmrs);
  } else {
    throw std::runtime_error(path + " is neither an SR progressive mesh nor an .srm");
  }
}

// SrMesh's view parameters for one camera and a tolerance of tau pixels.
//
// SrMesh's frame: v(0) the view direction, v(1) left, v(2) up, p() the eye,
// orthonormal. Its zooms are tan of the half angles to the top edge (zoomyx[0])
// and to the left edge (zoomyx[1]); square pixels give
// zoomyx = tan(fov_y / 2) * (1, width / height). Its screen-space test
// (SrMesh::big_error, Hoppe 1997) is pmjax's "small" test with
// kappa = screen_thresh * min(zoomyx) (SrMesh squares this into _tz2).
// pmjax's kappa is 2 tan(fov_y / 2) tau / height, so
//   screen_thresh = 2 tan(fov_y / 2) tau / (height * min(zoomyx)),
// which is 2 tau / min(width, height), SrMesh's own reading of a tolerance in
// pixels (SrViewParams::set_screen_thresh) when width >= height. The frustum:
// the four side planes and near (hither) and far (yonder), each tested against
// the bounding sphere, as pmjax's six planes.
SrViewParams view_params(const Camera& c, float tau) {
  const Point eye(c.eye[0], c.eye[1], c.eye[2]);
  const Point look(c.look[0], c.look[1], c.look[2]);
  const Vector forward = normalized(look - eye);
  Vector up(c.up[0], c.up[1], c.up[2]);
  const Vector left = normalized(cross(up, forward));
  up = cross(forward, left);
  SrViewParams vp;
  vp.set_frame(Frame(forward, left, up, eye));
  const double zoom_y = std::tan(0.5 * c.fov_y_deg * M_PI / 180.0);
  const double zoom_x = zoom_y * c.width / c.height;
  vp.set_zooms(V(float(zoom_y), float(zoom_x)));
  const double kappa = 2.0 * zoom_y * tau / c.height;
  vp.set_screen_thresh(float(kappa / std::min(zoom_y, zoom_x)));
  vp.set_hither(c.near);
  vp.set_yonder(c.far);
  return vp;
}

double thread_cpu_ms() {
  timespec t;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return 1e3 * double(t.tv_sec) + 1e-6 * double(t.tv_nsec);
}

// One pass along the path from the coarse mesh: per-frame milliseconds and
// active faces; returns the pass's CPU milliseconds.
double one_pass(SrMesh& srmesh, const std::vector<SrViewParams>& views, std::vector<double>& ms,
                std::vector<int>& faces) {
  srmesh.fully_coarsen();
  ms.assign(views.size(), 0.0);
  faces.assign(views.size(), 0);
  const double cpu0 = thread_cpu_ms();
  for (size_t i = 0; i < views.size(); i++) {
    const auto t0 = std::chrono::steady_clock::now();
    srmesh.set_view_params(views[i]);
    srmesh.adapt_refinement();
    const auto t1 = std::chrono::steady_clock::now();
    ms[i] = std::chrono::duration<double, std::milli>(t1 - t0).count();
    faces[i] = srmesh.num_active_faces();
  }
  return thread_cpu_ms() - cpu0;
}

void print_pass(std::ostream& os, const std::vector<double>& ms, const std::vector<int>& faces, double cpu_ms) {
  os << "ms";
  for (double t : ms) os << ' ' << t;
  os << "\nfaces";
  for (int n : faces) os << ' ' << n;
  os << "\ncpu_ms " << cpu_ms << '\n' << std::flush;
}

}  // namespace

int main(int argc, const char** argv) {
  try {
    if (argc < 4) {
      std::cerr << "usage: srmesh_adapt MESH.pm|MESH.srm CAMERAS.txt TAU [--passes N | --serve]\n";
      return 2;
    }
    const std::string mesh_path = argv[1], camera_path = argv[2];
    const float tau = std::stof(argv[3]);
    int passes = 1;
    bool serve = false;
    for (int i = 4; i < argc; i++) {
      const std::string arg = argv[i];
      if (arg == "--serve") {
        serve = true;
      } else if (arg == "--passes" && i + 1 < argc) {
        passes = std::stoi(argv[++i]);
      } else {
        throw std::runtime_error("unknown argument " + arg);
      }
    }
    if (!(tau > 0.f)) throw std::runtime_error("TAU must be > 0");
    std::vector<SrViewParams> views;
    for (const Camera& c : read_cameras(camera_path)) views.push_back(view_params(c, tau));
    SrMesh srmesh;
    read_srmesh(srmesh, mesh_path);
    std::vector<double> ms;
    std::vector<int> faces;
    if (serve) {
      // Answer each "pass" line with one pass; the caller alternates passes
      // with its own work. Ready once the mesh is read.
      std::cout << "ready " << views.size() << std::endl;
      for (std::string line; std::getline(std::cin, line);) {
        if (line == "quit") break;
        if (line != "pass") throw std::runtime_error("unknown command " + line);
        const double cpu_ms = one_pass(srmesh, views, ms, faces);
        print_pass(std::cout, ms, faces, cpu_ms);
      }
      return 0;
    }
    for (int p = 0; p < passes; p++) {
      const double cpu_ms = one_pass(srmesh, views, ms, faces);
      print_pass(std::cout, ms, faces, cpu_ms);
    }
    return 0;
  } catch (const std::exception& e) {
    std::cerr << "srmesh_adapt: " << e.what() << "\n";
    return 1;
  }
}
