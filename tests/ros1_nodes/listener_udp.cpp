// roscpp listener that asks for UDPROS first and TCPROS as the fallback
// (ros::TransportHints().unreliable().reliable()); prints GOT <data> per message.
#include <ros/ros.h>
#include <std_msgs/String.h>
#include <cstdio>

void on_message(const std_msgs::String::ConstPtr& m) {
  std::printf("GOT %s\n", m->data.c_str());
  std::fflush(stdout);
}

int main(int argc, char** argv) {
  ros::init(argc, argv, "roscpp_udp_listener", ros::init_options::NoSigintHandler);
  if (argc < 3) return 2;
  ros::NodeHandle nh;
  ros::Subscriber sub = nh.subscribe(argv[1], 100, on_message, ros::TransportHints().unreliable().reliable());
  std::printf("READY\n");
  std::fflush(stdout);
  ros::WallTime end = ros::WallTime::now() + ros::WallDuration(std::atof(argv[2]));
  while (ros::ok() && ros::WallTime::now() < end) {
    ros::spinOnce();
    ros::WallDuration(0.01).sleep();
  }
  return 0;
}
