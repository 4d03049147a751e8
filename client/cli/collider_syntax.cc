#include "collider_syntax.h"

#include <fmt/format.h>

#include <sstream>
#include <stdexcept>

#include "springblend/error.h"
#include "springblend/mesh.h"

namespace springblend::cli {

ColliderSpec ParseColliderSpec(const std::string& spec) {
  const auto colon = spec.find(':');
  if (colon == std::string::npos) {
    throw Error(ErrorCode::kInvalidInput,
                "collider '" + spec + "': expected KIND:VALUES (sphere:cx,cy,cz,r, capsule:x1,y1,z1,x2,y2,z2,r, "
                "box:cx,cy,cz,hx,hy,hz, plane:px,py,pz,nx,ny,nz or mesh:PATH)");
  }
  ColliderSpec out;
  out.kind = spec.substr(0, colon);
  const std::string rest = spec.substr(colon + 1);
  if (out.kind == "mesh") {
    out.path = rest;
    return out;
  }
  std::stringstream in(rest);
  for (std::string item; std::getline(in, item, ',');) {
    try {
      size_t used = 0;
      out.values.push_back(std::stod(item, &used));
      if (used != item.size()) throw std::invalid_argument(item);
    } catch (const std::exception&) {
      throw Error(ErrorCode::kInvalidInput, "collider '" + spec + "': '" + item + "' is not a number");
    }
  }
  size_t needed = 0;
  const char* syntax = "";
  if (out.kind == "sphere") needed = 4, syntax = "cx,cy,cz,r";
  if (out.kind == "capsule") needed = 7, syntax = "x1,y1,z1,x2,y2,z2,r";
  if (out.kind == "box") needed = 6, syntax = "cx,cy,cz,hx,hy,hz";
  if (out.kind == "plane") needed = 6, syntax = "px,py,pz,nx,ny,nz";
  if (needed == 0) {
    throw Error(ErrorCode::kInvalidInput,
                "collider '" + spec + "': unknown kind '" + out.kind + "' (sphere, capsule, box, plane or mesh)");
  }
  if (out.values.size() != needed) {
    throw Error(ErrorCode::kInvalidInput, fmt::format("collider '{}': {} takes {} numbers ({}), got {}", spec,
                                                      out.kind, needed, syntax, out.values.size()));
  }
  return out;
}

Collider ParseCollider(const std::string& spec) {
  const ColliderSpec c = ParseColliderSpec(spec);
  const std::vector<double>& v = c.values;
  if (c.kind == "mesh") return Collider::Mesh(LoadMesh(c.path));
  if (c.kind == "sphere") return Collider::Sphere({v[0], v[1], v[2]}, v[3]);
  if (c.kind == "capsule") return Collider::Capsule({v[0], v[1], v[2]}, {v[3], v[4], v[5]}, v[6]);
  if (c.kind == "box") return Collider::Box({v[0], v[1], v[2]}, {v[3], v[4], v[5]});
  return Collider::Plane({v[0], v[1], v[2]}, {v[3], v[4], v[5]});
}

}  // namespace springblend::cli
