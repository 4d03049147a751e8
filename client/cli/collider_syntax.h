// The command line's collider syntax (also the frames file's "colliders"): KIND:VALUES, parsed here rather than
// in the solver's public API, which takes Collider objects.
//   sphere:cx,cy,cz,r   capsule:x1,y1,z1,x2,y2,z2,r   box:cx,cy,cz,hx,hy,hz   plane:px,py,pz,nx,ny,nz
//   mesh:PATH (any mesh format LoadMesh reads)
#pragma once

#include <string>
#include <vector>

#include "springblend/collider.h"

namespace springblend::cli {

// The syntax split into its kind and numbers (or path), checked for their count.
struct ColliderSpec {
  std::string kind;            // sphere | capsule | box | plane | mesh
  std::vector<double> values;  // the numbers, in the syntax's order
  std::string path;            // mesh only
};

// Throws Error(kInvalidInput) naming the problem.
ColliderSpec ParseColliderSpec(const std::string& spec);

// The collider a spec describes (a mesh collider's file is loaded); throws Error naming the problem.
Collider ParseCollider(const std::string& spec);

}  // namespace springblend::cli
