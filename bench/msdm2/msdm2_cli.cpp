// Minimal driver around the reference MSDM2 implementation (Lavoue 2011) of MEPP2
// (MEPP-team/MEPP2, FEVV/Filters/CGAL/Surface_mesh/msdm2.h), for `python -m bench meshbench`.
//
//   msdm2_cli original.off degraded.off [levels [colours.txt]]  ->  "MSDM2 <value>"
//
// The value is MEPP2's one-way MSDM2 of the degraded mesh against the original (its
// process_msdm2_multires, `levels` scales, default 3); bench/meshbench.py runs both directions and
// averages them, as MEPP2's plugin does for its symmetric mode.  With a fourth argument the
// per-vertex colour map MEPP2's test_msdm2 writes is printed as "v x y z r g b" lines, to compare
// with its reference output (Testing/RefOutput/CGAL/Surface_mesh/cow_msdm2_reference.obj).
//
// Build (Debian 12: apt-get install libcgal-dev libboost-dev libeigen3-dev cimg-dev), from a
// checkout of MEPP2 (tested at commit d977d05):
//   g++ -O2 -std=c++17 -DNDEBUG -DFEVV_USE_CGAL -I MEPP2 -I /usr/include/eigen3 \
//       bench/msdm2/msdm2_cli.cpp -o msdm2_cli -lgmp -lmpfr
#include <CGAL/Cartesian.h>
#include <CGAL/Surface_mesh.h>
#include <CGAL/boost/graph/graph_traits_Surface_mesh.h>
#include "FEVV/Wrappings/Geometry_traits_cgal_surface_mesh.h"
#include "FEVV/Wrappings/Graph_traits_extension_cgal_surface_mesh.h"
#include "FEVV/Wrappings/properties_surface_mesh.h"
#include "FEVV/Filters/Generic/calculate_face_normals.hpp"
#include "FEVV/Filters/CGAL/Surface_mesh/msdm2.h"
#include "FEVV/Filters/Generic/minmax_map.h"
#include "FEVV/Filters/Generic/color_mesh.h"
#include <CGAL/IO/OFF.h>
#include <fstream>
#include <iostream>
#include <iomanip>

static bool load(const char *path, FEVV::MeshSurface &m) {
  std::ifstream in(path);
  return in && CGAL::IO::read_OFF(in, m);
}

int main(int argc, char **argv) {
  if (argc < 3) { std::cerr << "usage: msdm2_cli original.off degraded.off [levels]\n"; return 2; }
  FEVV::MeshSurface m_original, m_degraded;
  if (!load(argv[1], m_original) || !load(argv[2], m_degraded)) { std::cerr << "cannot read\n"; return 2; }
  FEVV::PMapsContainer bag_o, bag_d;
  auto pm_d = get(boost::vertex_point, m_degraded);
  auto pm_o = get(boost::vertex_point, m_original);
  auto fnm_d = make_property_map(FEVV::face_normal, m_degraded);
  auto fnm_o = make_property_map(FEVV::face_normal, m_original);
  FEVV::Filters::calculate_face_normals(m_degraded, pm_d, fnm_d);
  FEVV::Filters::calculate_face_normals(m_original, pm_o, fnm_o);
  auto msdm2_pmap = FEVV::make_vertex_property_map< FEVV::MeshSurface, double >(m_degraded);
  int levels = argc > 3 ? std::atoi(argv[3]) : 3;
  double value = -1;
  FEVV::Filters::process_msdm2_multires(m_degraded, pm_d, fnm_d, bag_d, m_original, pm_o, fnm_o, bag_o,
                                        levels, msdm2_pmap, value);
  std::cout << std::setprecision(10) << "MSDM2 " << value << std::endl;
  if (argc > 4) {  // the colour map as MEPP2's test_msdm2 writes it, to compare with its reference output
    auto lut = FEVV::Filters::make_LUT(false);
    auto v_cm = make_property_map(FEVV::vertex_color, m_degraded);
    put_property_map(FEVV::vertex_color, m_degraded, bag_d, v_cm);
    double lo, hi;
    FEVV::Filters::compute_min_max_vertices(m_degraded, msdm2_pmap, lo, hi);
    FEVV::Filters::color_vertices_from_map(m_degraded, msdm2_pmap, v_cm, lo, hi, lut);
    std::ofstream out(argv[4]);
    out << std::setprecision(10);
    for (auto v : vertices(m_degraded)) {
      auto p = get(pm_d, v);
      auto c = get(v_cm, v);
      out << "v " << p[0] << " " << p[1] << " " << p[2] << " " << c[0] << " " << c[1] << " " << c[2] << "\n";
    }
  }
  return 0;
}
